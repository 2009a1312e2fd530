"""The outside world: everything built on the sensor interface alone.

The service on the network (:mod:`biris_hw.io.net`), recordings and their replay
(:mod:`biris_hw.io.record`), the Foxglove live view (:mod:`biris_hw.io.liveview`), the ROS 2
payloads (:mod:`biris_hw.io.codec`), the one reader per sensor that feeds every sink
(:mod:`biris_hw.io.feed`), scan files, plots and sweeps. A module here reaches the sensor
through what any sensor offers (:class:`biris_hw.sensor.Sensor`) -- a local
:class:`~biris_hw.server.BirisServer`, a remote one or a replay -- and never imports the server,
the hardware layers or the simulator (an import-linter contract in ``pyproject.toml``): a new
adapter goes here, a new transport goes below (``biris_hw.bus``, ``biris_hw.irq``,
``biris_hw.axes``). docs/design.md, "Where things go".
"""
