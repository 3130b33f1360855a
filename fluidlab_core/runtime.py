"""Backend selection for the Taichi engine.

`init()` is the only place the package calls `ti.init`. Importing `fluidlab_core` does no work; building
a scene calls `ensure_init()`, which initialises the CPU backend in float32 when the user has not chosen.

Calling `init()` again with the same arguments does nothing. Calling it with different arguments resets
Taichi: simulators built before the reset are invalid and raise `RuntimeError` when used.

Fast compilation (`fast_compile=True`, or the environment variable FLUIDLAB_FAST_COMPILE=1, which processes
started from this one inherit): the solvers' forward kernels (the fast solver's step, the differentiable
solver's forward substep and its hand-written backwards, the gas solver's step: `compiled_fast`,
`fast_compilation`) compile at Taichi's `opt_level` 0, which skips
most of its own IR optimisation passes, where compile time goes. The physics is the same code; they compile
several times faster and run somewhat slower (`bench/fast_compile.py`, `bench/results/fast_compile_cpu.txt`).
Everything else keeps level 1: Taichi's automatic differentiation needs it (a `.grad` kernel would raise the
level to 1 for the rest of the process), and at level 0 Taichi 1.7.4's code generation fails on some kernels
(an LLVM "Instruction does not dominate all uses" abort, seen on a small kernel that adds numpy gradients into a
field's .grad). For the test suite and short jobs, whose time goes into compiling; long optimisations keep
the default.

Every `init` also raises Taichi's kernel cache to 1 GiB (OFFLINE_CACHE_BYTES) and, on Taichi 1.7, attaches lighter
debug strings to the statements it compiles (_lighter_source_positions): both for compile time, explained there.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import os
import time
from dataclasses import dataclass

ARCHES = ("auto", "cpu", "cuda")
PRECISIONS = ("f32", "f64")


@dataclass(frozen=True)
class RuntimeConfig:
    arch: str  # what the user asked for
    backend: str  # what runs: "cpu" or "cuda"
    precision: str
    seed: int | None
    cpu_threads: int | None
    fast_compile: bool
    generation: int  # bumped on every reset, so stale simulators can refuse to run
    debug: bool = False


_config: RuntimeConfig | None = None
_generation = 0


def _cuda_available(ti) -> bool:
    from taichi.lang.misc import is_arch_supported

    try:
        return bool(is_arch_supported(ti.cuda))
    except Exception:  # noqa: BLE001 - any failure to probe means "no CUDA"
        return False


def init(arch: str = "cpu", precision: str = "f32", seed: int | None = None,
         cpu_threads: int | None = None, debug: bool = False, fast_compile: bool | None = None,
         fresh: bool = False) -> RuntimeConfig:
    """Choose the Taichi backend.

    arch: "cpu" (default), "cuda", or "auto" (CUDA when a device is present, CPU otherwise).
    precision: "f32" or "f64" for every real-valued field.
    seed: seeds Taichi's random generator and the default particle sampling.
    cpu_threads: threads for the CPU backend (default: all cores, or FLUIDLAB_CPU_THREADS).
    fast_compile: compile the solvers' forward kernels at Taichi's opt_level 0 (default: off, or
    FLUIDLAB_FAST_COMPILE=1); see the module's docstring.
    fresh: reset Taichi even when the arguments are those already in force (see `reset`).
    """
    global _config, _generation
    if arch not in ARCHES:
        raise ValueError(f"arch must be one of {ARCHES}, got {arch!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if cpu_threads is None and os.environ.get("FLUIDLAB_CPU_THREADS"):
        cpu_threads = int(os.environ["FLUIDLAB_CPU_THREADS"])
    if fast_compile is None:
        flag = os.environ.get("FLUIDLAB_FAST_COMPILE", "").strip()
        if flag not in ("", "0", "1"):
            raise ValueError(f"FLUIDLAB_FAST_COMPILE must be 0 or 1, got {flag!r}")
        fast_compile = flag == "1"
    fast_compile = bool(fast_compile)
    same = _config is not None and (_config.arch, _config.precision, _config.seed, _config.cpu_threads,
                                    _config.fast_compile) == (arch, precision, seed, cpu_threads, fast_compile)
    if same and not fresh:
        return _config

    import taichi as ti

    if _config is not None:
        ti.reset()
    backend = arch
    if arch == "auto":
        backend = "cuda" if _cuda_available(ti) else "cpu"
    if backend == "cuda" and not _cuda_available(ti):
        raise RuntimeError("arch='cuda' was requested but Taichi finds no CUDA device; use arch='cpu' or 'auto'")
    kwargs = dict(
        arch=ti.cuda if backend == "cuda" else ti.cpu,
        default_fp=ti.f64 if precision == "f64" else ti.f32,
        default_ip=ti.i32,
        debug=debug,
        log_level=ti.WARN,
        offline_cache=True,
        kernel_profiler=bool(os.environ.get("FLUIDLAB_PROFILE")),
    )
    if not os.environ.get("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES"):
        kwargs["offline_cache_max_size_of_files"] = OFFLINE_CACHE_BYTES
    if seed is not None:
        kwargs["random_seed"] = int(seed)
    if cpu_threads:
        kwargs["cpu_max_num_threads"] = int(cpu_threads)
    ti.init(**kwargs)
    _lighter_source_positions(ti)
    _generation += 1
    _config = RuntimeConfig(arch, backend, precision, seed, cpu_threads, fast_compile, _generation, bool(debug))
    return _config


def reset() -> RuntimeConfig:
    """Reset Taichi and initialise it again as it was (or with the defaults): every field and compiled kernel of the
    process is dropped, and simulators built before raise RuntimeError when used.

    What it is for: Taichi's offline cache finds a compiled kernel by the kernel's code and the identities of the
    fields it touches (their SNode ids and tree ids, which count up from the start of the program), so a scene
    compiles again whenever other fields were allocated before it, though the same scene compiled earlier in the
    same process or in another one. After a reset the ids start from zero, so a scene built right after one has the
    same field identities wherever it is built, and its kernels load from the cache when the same build ran before
    (the held disc of tests/test_physics_solids.py: 3.5 s to 1.1 s a run from the second on). The test suite resets
    before each run of a sweep that builds the same scene again (tests/conftest.py, `fresh`)."""
    c = _config
    if c is None:
        return init(fresh=True)
    return init(c.arch, c.precision, c.seed, c.cpu_threads, debug=c.debug, fast_compile=c.fast_compile, fresh=True)


# Taichi keeps compiled kernels on disk (its offline cache) and by default, past 100 MB, deletes the least recently
# used quarter of it when a program ends (policy "lru", factor 0.25). The package's kernels are specialised to their
# fields' shapes, so a few tasks at two sizes, the gas solver and the gradients pass 100 MB (a cold run of the test
# suite did within the run), and a process that ends (a test worker, a command line, a ROS node) may evict kernels
# that the next one must compile again. 1 GiB, unless TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES says otherwise.
OFFLINE_CACHE_BYTES = 1 << 30


def _lighter_source_positions(ti) -> None:
    """Taichi 1.7's frontend attaches to every statement of every kernel it transforms a debug string: the statement's
    source lines wrapped to 80 columns with a caret line under them (ASTTransformerContext.get_pos_info, through
    textwrap). That was about 40 % of the Python side of compiling (the gas plume's first step with a warm kernel
    cache: 11.1 s, 6.9 s with this), paid by every process, since the cache keeps compiled kernels and not the
    transformed source. This keeps the file, line, function and source line of each statement, without the wrapping
    and the carets. Applied only to the Taichi minor version it was written against; otherwise nothing changes."""
    try:
        from taichi.lang.ast import ast_transformer_utils as utils
    except ImportError:  # pragma: no cover - another Taichi layout
        return
    ctx = getattr(utils, "ASTTransformerContext", None)
    if tuple(ti.__version__[:2]) != (1, 7) or ctx is None or getattr(ctx, "_fluidlab_positions", False):
        return

    def get_pos_info(self, node):
        return (f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n'
                f"{self.src[node.lineno - 1]}\n")

    ctx.get_pos_info = get_pos_info
    ctx._fluidlab_positions = True


@contextlib.contextmanager
def fast_compilation():
    """Under fast compilation, the kernels that compile inside this block (at their first launch) compile at
    Taichi's opt_level 0 (see the module's docstring); otherwise nothing changes. For forward kernels and the
    hand-written backwards, which are plain kernels; not for Taichi's reverse-mode (`.grad`) kernels."""
    if _config is None or not _config.fast_compile:
        yield
        return
    from taichi.lang import impl

    cfg = impl.current_cfg()
    saved = cfg.opt_level
    cfg.opt_level = 0
    try:
        yield
    finally:
        cfg.opt_level = saved


def compiled_fast(method):
    """Decorator for the solvers' forward methods: the kernels they launch compile inside `fast_compilation`."""

    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with fast_compilation():
            return method(*args, **kwargs)

    return wrapper


def ensure_init() -> RuntimeConfig:
    """The current configuration, initialising the CPU/f32 default if `init` was never called."""
    return _config if _config is not None else init()


def current() -> RuntimeConfig | None:
    return _config


def real_dtype():
    import taichi as ti

    return ti.f64 if ensure_init().precision == "f64" else ti.f32


def numpy_real():
    import numpy as np

    return np.float64 if ensure_init().precision == "f64" else np.float32


def scatter_copies() -> int:
    """Per-thread grid copies for the scatters of the solvers (engine/transfer.py): one per CPU thread on the
    CPU, 0 (atomic scatters) on CUDA. On the CPU, FLUIDLAB_SCATTER_COPIES overrides it (0 runs the GPU's atomic
    code path, as the tests do; on a many-core CPU fewer copies than threads may be faster, docs/engine.md)."""
    cfg = ensure_init()
    if cfg.backend != "cpu":
        return 0
    if os.environ.get("FLUIDLAB_SCATTER_COPIES"):
        return int(os.environ["FLUIDLAB_SCATTER_COPIES"])
    return cfg.cpu_threads or os.cpu_count() or 1


# --- compilation notices -------------------------------------------------------------------------------
# Taichi compiles a kernel the first time it runs, so a simulator's first step (and its first gradient
# rollout) can take a minute on two cores while later ones take milliseconds. Whoever shows progress hears
# of it: the `fluidlab` command prints a line before and after, sim_node's fluid worker tells the node.
_compile_listener = None
_log = logging.getLogger("fluidlab_core")


def on_compile(listener):
    """Set the process-wide listener(phase, what, seconds) told when a first run compiles kernels: phase
    "start" (seconds 0) and "done" (seconds the first run took, compilation included). None restores the
    default, a logging message on the "fluidlab_core" logger. Returns the previous listener."""
    global _compile_listener
    previous, _compile_listener = _compile_listener, listener
    return previous


@contextlib.contextmanager
def compiling(what: str, done=None):
    """Wrap a first run that compiles `what` (e.g. "the simulator's kernels"), telling the listener; `done()` is
    called when the run succeeded (a run that failed is announced again the next time)."""
    listener = _compile_listener or (lambda phase, name, seconds: _log.info(
        "compiling %s ..." % name if phase == "start" else "%s compiled and ran in %.1f s" % (name, seconds)))
    listener("start", what, 0.0)
    t0 = time.perf_counter()
    yield
    listener("done", what, time.perf_counter() - t0)
    if done is not None:
        done()
