"""Compile-speed tricks, private to the package: exported programs kept beside the persistent
cache (``aot``), programs compiled in a worker thread ahead of their stage (``ahead``), and
programs compiled without LLVM's optimizations where that is faster overall
(``quick_compile``). Science modules call them; users never need to."""
