"""Subcommands of `controlled-islanding`, one module each (see controlled_islanding/cli.py)."""
