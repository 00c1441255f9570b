"""``python -m diffkin.kernels``: build (or find in the cache) the fused native kernel and print where it is;
without a C compiler, say so and why (the torch kernels then serve every call). Exit status 0 either way:
the kernel is an optimisation, not an install requirement."""

from .native import _main

if __name__ == "__main__":  # importing this module (docs tools, scanners) must not exit
    raise SystemExit(_main())
