"""The ``biris`` subcommands, one module each, and the modules they share.

Every command module has the same two functions, which is all the dispatcher
(:mod:`biris_hw.cli`) knows about it: ``add_arguments(parser)`` declares its flags and
``run(args) -> int`` does the work and returns the exit status. A command's module is imported
only when that command runs, and importing it loads nothing of the server, the hardware or the
outside world (they are imported inside ``run``), so ``biris COMMAND --help`` never pays for a
server or matplotlib.

What the commands share, by job:

* :mod:`~biris_hw.commands.argtypes`: the argument types (``biris sim`` and ``biris regdump``
  use them too);
* :mod:`~biris_hw.commands.options`: the flags every command that talks to the sensor takes,
  how they are checked together, and the output files checked before the sensor is touched;
* :mod:`~biris_hw.commands.session`: opening the sensor those flags name
  (:func:`~biris_hw.opening.open_sensor`, plus the simulator's lag warning and audit), and
  asking before a long turn of a real head;
* :mod:`~biris_hw.commands.console`: what a person is told on stderr while a command works;
* :mod:`~biris_hw.commands.failures`: errors as one line, and the exit statuses;
* :mod:`~biris_hw.commands.faults`: how the long-running commands live through a fault.

Library code the commands share with programs is not here: opening a sensor is
:mod:`biris_hw.opening`, continuous sweeps :mod:`biris_hw.io.sweeps`, scan files
:mod:`biris_hw.io.scanfile`.
"""
