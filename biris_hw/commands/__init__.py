"""The ``biris`` subcommands, one module each.

Every module has the same two functions, which is all the dispatcher (:mod:`biris_hw.cli`)
knows about it: ``add_arguments(parser)`` declares its flags and ``run(args) -> int`` does the
work and returns the exit status. Modules are imported only when their command runs, so
``biris --help`` or ``biris watch`` never pays for matplotlib. The argument types every command
uses (``biris sim`` and ``biris regdump`` too) live in :mod:`biris_hw.commands.argtypes`; shared
flags, opening the sensor and turning errors into one line in :mod:`biris_hw.commands.common`.
Library code the commands share with programs is not here: continuous sweeps are
:mod:`biris_hw.io.sweeps`, scan files :mod:`biris_hw.io.scanfile`.
"""
