"""Benchmarks behind ``codecsplat bench NAME``: each module NAME exposes ``run(args) -> dict``; their command-line
options are in :mod:`.options` (torch-free, so that the command line answers ``--help`` at once)."""
