"""Subcommands of ``meshbench``; see ``benchmarks.cli.COMMANDS``."""
