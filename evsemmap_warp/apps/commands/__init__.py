"""The ``evsemmap`` commands, one module each: ``add_parser(sub)`` adds the command's flags to the
subcommands, ``run(args)`` does its work and returns the exit code (``apps/cli.py`` composes them)."""
