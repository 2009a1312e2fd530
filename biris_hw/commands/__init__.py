"""The ``biris`` subcommands, one module each.

Every module has the same two functions, which is all the dispatcher (:mod:`biris_hw.cli`)
knows about it: ``add_arguments(parser)`` declares its flags and ``run(args) -> int`` does the
work and returns the exit status. Modules are imported only when their command runs, so
``biris --help`` or ``biris watch`` never pays for matplotlib. Shared flags, opening the sensor
and turning errors into one line live in :mod:`biris_hw.commands.common`.
"""
