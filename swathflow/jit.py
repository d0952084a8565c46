"""numba's ``njit`` for the compiled kernels, with a lighter load of its on-disk cache.

Loading a cached kernel (``cache=True``), numba first refreshes its whole typing and
target context (``BaseContext.refresh``): it imports some 60 modules of its compiler
(array, linalg, random, typed containers, unicode, ...) and installs their typing and
lowering registries. A cached kernel needs none of that, only numba's runtime (NRT),
whose missing start is what the refresh was added for (numba #2198). On a process's
first kernel the refresh cost 0.12 CPU-s (0.08-0.1 for the refresh, 0.04 for numba's
array target loaded before it), in every command and every worker process. numba's
maintainers explored the same (numba PR #9806: refresh only for object mode, which our
kernels do not use).

:func:`njit` is numba's ``njit``; with ``cache=True`` the dispatcher's cache loads a
kernel after starting the NRT alone (its functions loaded from object code kept beside
the cache, not compiled in every process: :func:`_start_runtime`), and without importing
the numba modules whose functions the kernel was linked with (:func:`_envs_unimported`),
its LLVM bitcode (kept for inlining into later compilations) left unparsed until one
links it (:func:`_links_unparsed`).
On a cache miss numba compiles as usual (its compiler refreshes the contexts itself).
Where numba's cache does not have the methods this relies on (another numba), the kernel
keeps numba's own cache.

For code without Python objects (no ``objmode``, no typed dict, set or string hashing,
whose symbols come from modules the refresh imports): swathflow's kernels and those of
its sensor plugins. Kernels of another kind use numba's ``njit``.
"""
from __future__ import annotations

import contextlib
import os
import socket
import sys

import numba
from llvmlite import binding as ll
from numba.core import codegen
from numba.core.caching import FunctionCache

from swathflow.startup import blas_probe_alone, lean_numba_arrays

__all__ = ["cached", "compiling_alone", "njit"]


def cached(kernel) -> bool:
    """Whether numba's on-disk cache holds ``kernel`` (a dispatcher with ``cache=True``):
    False on the first run after an install or a clone, when numba compiles the kernels
    (about a minute more for a whole run on 2 cores; later runs load them). True where
    this numba does not say (no cache index path)."""
    try:
        return os.path.exists(kernel._cache._cache_file._index_path)
    except AttributeError:
        return True


@contextlib.contextmanager
def compiling_alone(kernel, timeout: float = 600.0):
    """While numba's cache lacks ``kernel`` (a new install): hold an exclusive lock on a
    file of this host in the folder numba caches it in, so that the processes running the
    same block on this machine (a local cluster's workers) take turns: the first compiles
    and caches the kernels, the others wait, then load them instead of compiling them
    again side by side (each the same 25-50 CPU-s). With the cache full, or no lock to be
    had (no such folder, no ``fcntl``), the block runs at once; after ``timeout`` s of
    waiting too. The system drops the lock of a process that dies. Yields whether the
    cache lacked ``kernel`` on entry."""
    fd = None
    cold = not cached(kernel)
    if cold:
        with contextlib.suppress(Exception):   # noqa: BLE001 - no lock: compile alongside
            import fcntl
            # one lock a host: the processes of one machine (one CPU, one entry of numba's
            # cache) take turns; those of other hosts sharing the folder do not wait
            path = os.path.join(kernel._cache._cache_path,
                                f"swathflow-compile.{socket.gethostname()}.lock")
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
            _lock(fd, fcntl, timeout)
    try:
        yield cold
    finally:
        if fd is not None:
            os.close(fd)                            # the lock goes with the descriptor


def _lock(fd: int, fcntl, timeout: float) -> None:
    """``flock(fd, LOCK_EX)``, given up after ``timeout`` s (polled)."""
    import time
    end = time.monotonic() + timeout
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > end:
                return
            time.sleep(0.1)


class _LightCache(FunctionCache):
    """numba's per-function cache, loading without the context refresh."""

    def load_overload(self, sig, target_context):
        _start_runtime(target_context)         # once a process; the kernels allocate
        cres = None
        # a kernel's environment may name numba's array target (loaded as it unpickles)
        with blas_probe_alone(), _envs_unimported(), _links_unparsed(), \
                self._guard_against_spurious_io_errors():
            cres = self._load_overload(sig, target_context)
        if cres is None:        # numba compiles it now, its contexts refreshed by its compiler
            lean_numba_arrays()     # (their array target without the scipy.linalg package)
        return cres


def _start_runtime(target_context) -> None:
    """Start numba's runtime (``rtsys.initialize``) with its compiled functions (reference
    counting, allocation: a small LLVM module that numba compiles in every process, 0.04-0.08
    s) loaded from their object code, kept beside the kernels' cache
    (:func:`_runtime_library`)."""
    from numba.core.runtime import nrtdynmod, rtsys
    if getattr(rtsys, "_init", False):
        return
    compile_ = getattr(nrtdynmod, "compile_nrt_functions", None)
    if compile_ is None or not hasattr(nrtdynmod, "create_nrt_module"):
        rtsys.initialize(target_context)               # another numba: its own way
        return
    nrtdynmod.compile_nrt_functions = _runtime_library
    try:
        rtsys.initialize(target_context)
    finally:
        nrtdynmod.compile_nrt_functions = compile_


def _runtime_library(ctx):
    """numba's ``compile_nrt_functions(ctx)``, its result kept as object code in a file
    named by numba's and llvmlite's versions and the machine's code generation (target,
    CPU, features: numba's own cache key), in the folder numba caches this module's
    kernels in; written atomically; a file that does not load is compiled again."""
    import hashlib
    import pickle

    import llvmlite
    from numba.core.runtime import nrtdynmod
    codegen = ctx.codegen()
    key = hashlib.sha256(repr((numba.__version__, llvmlite.__version__,
                               codegen.magic_tuple())).encode()).hexdigest()[:20]
    try:
        path = os.path.join(FunctionCache(_anchor)._cache_path, f"jit.nrt-{key}.nbo")
    except Exception:  # noqa: BLE001 - no cache folder: compiled as numba does
        path = None
    if path is not None:
        try:
            with open(path, "rb") as f:
                return codegen.unserialize_library(pickle.load(f))
        except Exception:  # noqa: BLE001 - missing, stale or damaged: compiled again
            pass
    ir_module, library = nrtdynmod.create_nrt_module(ctx)
    library.enable_object_caching()
    library.add_ir_module(ir_module)
    library.finalize()
    if path is None:
        return library
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as f:
            pickle.dump(library.serialize_using_object_code(), f)
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            os.remove(tmp)
    return library


@contextlib.contextmanager
def _links_unparsed():
    """A kernel cached as object code also carries its LLVM bitcode, for inlining into
    kernels compiled later that call it; numba parses it and lists its symbols as the
    kernel loads (about 0.06 s of the rectify engine's 17 kernels, in every process).
    Inside this block such a kernel loads as a :class:`_LinkedLater` library: the bitcode
    is parsed when a compilation first links it (never, with the cache full)."""
    base = codegen.JITCodeLibrary
    if "_unserialize" in base.__dict__ or not all(hasattr(base, a) for a in (
            "_unserialize", "enable_object_caching", "_set_compiled_object",
            "_finalize_final_module", "_ensure_finalized")):
        yield                # loading already (a numba lock holds loads one at a time),
        return               # or another numba: its own way
    unserialize = codegen.CPUCodeLibrary._unserialize.__func__

    def unserialize_later(cls, cg, state):
        name, kind, data = state
        if cls is not base or kind != "object" or not isinstance(data, tuple) \
                or len(data) != 2:
            return unserialize(cls, cg, state)
        object_code, bitcode = data
        lib = cg.create_library(name)
        lib.__class__ = _LinkedLater
        lib._bitcode = bitcode
        lib.enable_object_caching()
        lib._set_compiled_object(object_code)
        lib._finalize_final_module()
        return lib

    base._unserialize = classmethod(unserialize_later)
    try:
        yield
    finally:
        del base._unserialize


class _LinkedLater(codegen.JITCodeLibrary):
    """A kernel's library loaded from object code (:func:`_links_unparsed`), its bitcode
    (``_bitcode``) parsed and its symbols listed when first asked for: when a new
    compilation links it."""

    @property
    def _shared_module(self):
        mod = self.__dict__.get("_shared")
        if mod is None and self.__dict__.get("_bitcode") is not None:
            mod = ll.parse_bitcode(self.__dict__.pop("_bitcode"))
            self._codegen._engine._load_defined_symbols(mod)
            self.__dict__["_shared"] = mod
        return mod

    @_shared_module.setter
    def _shared_module(self, mod):
        self.__dict__["_shared"] = mod

    def get_pointer_to_function(self, name):
        """The address of ``name`` in the loaded object code (0: not there), without
        numba's list of the symbols defined."""
        self._ensure_finalized()
        return self._codegen._engine.get_function_address(name)


def _anchor():
    """A function of this module: numba's cache folder for it holds the runtime's file."""


@contextlib.contextmanager
def _envs_unimported():
    """A cached kernel names the environment of every numba function it was linked with
    (``np.empty``'s, ``np.searchsorted``'s, an integer's ``str``...): the globals of the
    numba module that defines it, imported as the kernel unpickles (``_rebuild_env``):
    ``numba.np.arrayobj``, ``arraymath``, ``npyimpl``, ``cpython.unicode``... (about 25
    modules: 0.07 s of the rectify engine's kernel loads, 0.14 s of the mosaic's four).
    Compiled code reads those globals only in object mode, which numba's own
    implementations do not use. Inside this block such an environment, of a numba module
    not loaded yet, gets the module's name alone for its globals (its constants as
    pickled), and is not memoised: a later compilation that needs the same environment
    makes numba's own, from the module then imported."""
    from numba.core import environment
    rebuild = getattr(environment, "_rebuild_env", None)
    if rebuild is None or not hasattr(environment, "lookup_environment"):
        yield                                  # another numba: its own way
        return

    def rebuild_unimported(modname, consts, env_name):
        env = environment.lookup_environment(env_name)
        if env is not None or modname in sys.modules or \
                not str(modname).startswith("numba."):
            return env if env is not None else rebuild(modname, consts, env_name)
        env = environment.Environment({"__name__": modname})
        env.consts[:] = consts
        env.env_name = env_name
        return env

    environment._rebuild_env = rebuild_unimported
    try:
        yield
    finally:
        environment._rebuild_env = rebuild


_USABLE = all(hasattr(FunctionCache, a) for a in (
    "load_overload", "_load_overload", "_guard_against_spurious_io_errors"))


def njit(fn=None, **options):
    """``numba.njit(fn, **options)`` (also as ``@njit(**options)``); with ``cache=True``
    its cache loads as :class:`_LightCache`."""
    if fn is None:
        return lambda f: njit(f, **options)
    d = numba.njit(fn, **options)
    if _USABLE and type(getattr(d, "_cache", None)) is FunctionCache:
        d._cache.__class__ = _LightCache           # same state, one method differs
    return d
