"""Pure Warp kernels (installed as ``warpnerf.kernels``). No torch import here.

Each module is one kernel family with ``*_fwd`` / ``*_bwd`` kernels; importing a module registers
its float32 and float64 overloads but compiles nothing (Warp compiles a module at its first launch).
"""
