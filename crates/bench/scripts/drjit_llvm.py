"""Which libLLVM Dr.Jit loads, for the Mitsuba 3 comparison scripts.

Mitsuba 3.9 / Dr.Jit 1.5 emit the llvm.minimum/maximum intrinsics, which the
x86 backend of LLVM 16 and older cannot compile: the first kernel then aborts
the process with "LLVM ERROR: Cannot select: ... fminimum". Dr.Jit loads
whichever libLLVM it finds (Debian 12: LLVM 15) unless DRJIT_LIBLLVM_PATH
names one, so this must run before mitsuba is imported.
"""

import os

MIN_LLVM_MAJOR = 17


def choose(llvm=None):
    """Sets DRJIT_LIBLLVM_PATH: `llvm` when given, else what the environment
    says, else the newest system libLLVM new enough (Debian: apt-get install
    libllvm19), so the benchmarks need no flag where one is installed."""
    if llvm:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
        return
    if "DRJIT_LIBLLVM_PATH" in os.environ:
        return
    for major in range(30, MIN_LLVM_MAJOR - 1, -1):
        lib = f"/usr/lib/x86_64-linux-gnu/libLLVM-{major}.so"
        if os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
            return
