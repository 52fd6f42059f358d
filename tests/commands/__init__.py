"""Tests of service.commands: the bdsfix subcommands and their errors."""
