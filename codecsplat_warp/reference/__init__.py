"""Plain-torch reference implementations (dense, slow, obviously correct) that tests, ``selfcheck`` and
benchmarks compare the Warp kernels against. They share the conventions of :mod:`codecsplat_warp.cameras`.
"""
