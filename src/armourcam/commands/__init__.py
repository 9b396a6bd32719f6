"""Subcommands of ``armourcam``: each module defines ``register(subparsers)``.

Every module in this package is discovered and registered by :mod:`armourcam.cli`; a command module
only parses its arguments and calls the cores.
"""
