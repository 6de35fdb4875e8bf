"""OpenBLAS kernels: which one this process runs, which ones this CPU can run, and the
environment that makes a process take another, so that one machine can show what another
CPU would compute.

numpy and scipy ship OpenBLAS built for every x86-64 CPU kind (DYNAMIC_ARCH); at start it
picks the kernels of the CPU it finds, or those named by ``OPENBLAS_CORETYPE``. The kernels
block and sum matrix products in different orders, so a product of the same numbers can
differ in its last bits from one CPU kind to another (measured: a learning session's results
by up to 4.3e-11 relative after hundreds of rollouts, docs/testing.md "What is equal to what"). Used by the
suite's kernel sweeps (`run_per_kernel`) and by the learning identity
(`psl_bench.learning_identity`).
"""
from __future__ import annotations

import os

# kernel (as OpenBLAS names the one it took) -> the CPU flags it needs; a kernel the CPU
# lacks would end the process with an illegal instruction
KERNELS = {'Katmai': {'sse2'}, 'Nehalem': {'ssse3', 'sse4_2'}, 'Sandybridge': {'avx'},
           'Haswell': {'avx2', 'fma'},
           'SkylakeX': {'avx512f', 'avx512bw', 'avx512dq', 'avx512vl'}}


def cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux /proc/cpuinfo; empty elsewhere)."""
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('flags'):
                    return set(line.split(':', 1)[1].split())
    except OSError:
        pass
    return set()


def runnable_kernels() -> list[str]:
    """The kernels of KERNELS this CPU has the instructions for, oldest first."""
    flags = cpu_flags()
    return [kernel for kernel, needs in KERNELS.items() if needs <= flags]


def current_kernel() -> str:
    """The kernel numpy's OpenBLAS runs in this process ('' if numpy has no OpenBLAS)."""
    __import__('numpy')          # loads the library threadpoolctl inspects
    from threadpoolctl import threadpool_info
    kernels = sorted({i.get('architecture', '') for i in threadpool_info()
                      if i.get('internal_api') == 'openblas'})
    return kernels[0] if kernels else ''


def environment(kernel: str) -> dict[str, str]:
    """This process's environment with OpenBLAS told to take `kernel`.

    Raises:
        ValueError: an unknown kernel, or one this CPU cannot run.
    """
    if kernel not in KERNELS:
        raise ValueError(f'unknown OpenBLAS kernel {kernel!r}: one of {", ".join(KERNELS)}')
    if kernel not in runnable_kernels():
        raise ValueError(f'this CPU cannot run the OpenBLAS kernel {kernel!r} (it lacks '
                         f'{", ".join(sorted(KERNELS[kernel] - cpu_flags()))})')
    return {**os.environ, 'OPENBLAS_CORETYPE': kernel}


def run_per_kernel(arguments: list[str], timeout: float = 300.0) -> dict[str, str]:
    """``python -m pytest ARGUMENTS`` once per kernel this CPU runs but the one this process
    runs (the suite runs the tests with that one already), one after the other, each
    in a session of its own with OpenBLAS told to take that kernel and ``PSL_OPENBLAS_SWEEP``
    naming it: kernel -> its output. First checks that a process started so takes the kernel.
    Raises AssertionError naming the kernel when a run fails or times out (its process group
    is ended then, and when anything else goes wrong); ValueError when this CPU offers no
    choice of kernel (no x86-64 flags: tests say so by skipping)."""
    import signal
    import subprocess
    import sys
    kernels = [k for k in runnable_kernels() if k != current_kernel()]
    if not kernels:
        raise ValueError('no x86-64 CPU flags found (or one kernel only): OpenBLAS kernels '
                         'cannot be chosen here')
    outputs = {}
    for kernel in kernels:
        env = {**environment(kernel), 'PSL_OPENBLAS_SWEEP': kernel}
        taken = subprocess.run([sys.executable, '-c', 'from psl_bench.openblas import '
                                'current_kernel; print(current_kernel())'], env=env,
                               capture_output=True, text=True, timeout=60)
        assert taken.stdout.strip() == kernel, \
            f'OPENBLAS_CORETYPE={kernel} took {taken.stdout.strip()!r}: {taken.stderr}'
        run = subprocess.Popen([sys.executable, '-m', 'pytest', '-q', '-p', 'no:randomly',
                                '-p', 'no:cacheprovider', *arguments], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True)
        try:
            out, _ = run.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            out = f'(no end within {timeout:g} s)'
        finally:
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait(timeout=10)
        assert run.returncode == 0, f'with the {kernel} kernel:\n{out[-3000:]}'
        outputs[kernel] = out
    return outputs
