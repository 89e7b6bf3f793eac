"""Benchmarks behind ``codecsplat bench NAME``; each module exposes ``add_arguments(parser)`` and ``run(args) -> dict``."""
