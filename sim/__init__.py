"""The BIRIS hardware simulator: it plays the far side of the driver's windows and lines."""

POISON = 0x7A7A
"""The value every element of a frame holds while that frame is being exposed."""

__all__ = ["POISON"]
