"""ctypes mirrors and self-describing register sets for the BIRIS hardware.

Modules: :mod:`regs.biexec` (the BIEXEC_COM control block), :mod:`regs.layout` (the BIRIS memory
map), :mod:`regs.hctl1000` (the motion-control chip), :mod:`regs.tech80` (the Model 7600 board)
and :mod:`regs.bit3` (the Model 412 coupler). Everything is big-endian, 68020 alignment.
"""
