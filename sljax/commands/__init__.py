"""Subcommands of the `sljax` CLI.

Each module here defines `register(subparsers)`, which adds one subparser whose
`func(args)` runs the command (heavy imports inside `func`, so `--help` stays fast).
"""
