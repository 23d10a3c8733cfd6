"""Compile-speed tricks, private to the package: exported programs kept beside the persistent
cache (`aot`), libraries padded to a few sizes so that one sampler program serves each
(`buckets`), short-running programs compiled without LLVM's optimizations and the others at
its level 2 in a process set up for the CPU (`quick_compile`), and arguments' weak types
kept out of programs' keys (`keys`). Science modules use them through decorators and the
sampler's driver; no science function takes a trick parameter, and users never need them
(`benchmarks/tricks.py` measures each against plain `jit` with the persistent cache)."""
