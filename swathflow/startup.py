"""A process's start: imports without the parts a command does not use, and without the
garbage collector's passes over the objects that live to the end.

One place for the tricks that the rectify command (its serial start, before its workers
fork) and the mosaic (numba's first load) use on their start-up; the Python API imports
as usual.
"""
from __future__ import annotations

import contextlib
import gc
import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
import threading
from importlib import import_module

__all__ = ["uncollected", "import_without", "underived_docstrings", "blas_probe_alone",
           "lean_numba_arrays", "lazy_modules"]


@contextlib.contextmanager
def uncollected(freeze: bool = True):
    """No collector passes inside the block (an engine's imports and numba's start make
    some 100 000 objects that all live to the end: the passes over them while they are
    made cost 0.1-0.2 CPU-s), and with ``freeze`` the objects then alive moved out of the
    collector's reach after it (``gc.freeze``: later full collections and the
    interpreter's last ones at exit no longer walk them; they are still freed by reference
    counting). Freeze once a process: a reference cycle alive at that moment is kept. The
    collector's state is restored after."""
    on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
        if on:
            gc.enable()


def import_without(names: str | tuple[str, ...], module: str) -> None:
    """Import ``module`` (unless loaded already) while an import of ``names`` (one module
    name or several) fails (ImportError); the usual way when one of ``names`` is loaded
    already or ``module`` cannot do without them after all. ``names`` stay importable
    afterwards.

    Used for ``dask.array``: its ``fft`` module imports ``scipy.fftpack`` only to warn
    about ``fft_wrap(scipy.fftpack...)`` (with it ``scipy.fft`` and ``scipy.special``, 53
    modules, 0.08-0.1 CPU-s), and its ``chunk_types`` imports ``scipy.sparse`` only to
    accept sparse matrices as chunks (with it ``scipy._lib``'s array-API shims,
    ``numpy.testing`` and ``numpy.f2py``: 120 modules, about 0.05 CPU-s).

    Only on a process's main thread while no other thread imports: the modules held back
    are unimportable for every thread meanwhile."""
    held = (names,) if isinstance(names, str) else tuple(names)
    if module in sys.modules:
        return
    if not any(n in sys.modules for n in held):
        for n in held:
            sys.modules[n] = None         # an import of it fails while ``module`` loads
        try:
            import_module(module)
        except ImportError:
            pass
        finally:
            for n in held:
                if sys.modules.get(n, 0) is None:
                    del sys.modules[n]
    import_module(module)


@contextlib.contextmanager
def underived_docstrings():
    """dask's array functions and methods derive their docstrings from numpy's when they
    are defined (``dask.utils.derived_from``: some 300 of them on ``import dask.array``,
    each a copy of numpy's text with its unsupported keywords marked: about 0.16 CPU-s,
    half of that import). Inside this block they keep their own docstrings instead (what
    ``derived_from`` would add to). A name the original lacks still gives dask's function
    that raises NotImplementedError. Only for a process that never shows dask's help; the
    functions defined after the block get dask's docstrings again. Nothing is changed when
    ``dask.utils`` has no ``_derived_from``."""
    try:
        from dask import utils
        derive = utils._derived_from
    except (ImportError, AttributeError):
        yield
        return

    def own(cls, method, *args, extra="", **kwargs):
        getattr(cls, method.__name__)      # dask's AttributeError where cls lacks it
        return extra or None

    utils._derived_from = own
    try:
        yield
    finally:
        utils._derived_from = derive


@contextlib.contextmanager
def blas_probe_alone():
    """numba probes for BLAS with ``import scipy.linalg.cython_blas`` when its array target
    loads (``numba.np.arraymath``: on a process's first compiled call, or when a cached
    kernel's environment names it), which runs the whole ``scipy.linalg`` package
    (0.1-0.27 CPU-s: array-API shims, docstring parsing, ``numpy.f2py``): about half of
    numba's start, for kernels that never use ``scipy.linalg``. If the array target loads
    inside this block, that module is the extension file alone, loaded by the standard
    loader under its own name just before (numba's BLAS wrappers get their function
    pointers from it as from the package's). It leaves ``sys.modules`` after the block, so
    a later ``import scipy.linalg`` runs the package as usual and binds the same module
    object (an extension is initialised once per process). Nothing is done when the
    array target does not load in the block, ``scipy.linalg`` is loaded already or the
    file is not found."""
    watch = _ArrayTargetWatch()
    sys.meta_path.insert(0, watch)
    try:
        yield
    finally:
        sys.meta_path.remove(watch)
        if watch.added:
            sys.modules.pop(_BLAS, None)


_BLAS = "scipy.linalg.cython_blas"


class _ArrayTargetWatch(importlib.abc.MetaPathFinder):
    """As ``numba.np.arraymath`` is about to load: ``scipy.linalg``'s BLAS extension put in
    ``sys.modules`` alone (``added``), unless that package or module is there already."""

    def __init__(self):
        self.added = False

    def find_spec(self, fullname, path, target=None):
        if fullname == "numba.np.arraymath" and not self.added and \
                "scipy.linalg" not in sys.modules and _BLAS not in sys.modules:
            module = _extension_alone(_BLAS)
            if module is not None:
                sys.modules[_BLAS] = module
                self.added = True
        return None                           # the usual finders find the module itself


def _extension_alone(name: str):
    """``scipy.linalg``'s extension module ``name`` loaded without its package, or None."""
    try:
        import scipy
        spec = importlib.machinery.PathFinder.find_spec(
            name, [os.path.join(p, "linalg") for p in scipy.__path__])
        if spec is None or spec.loader is None:
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    except ImportError:
        return None


def lean_numba_arrays() -> None:
    """Load numba's array target (``numba.np.arraymath``) with its BLAS probe satisfied by
    :func:`blas_probe_alone`, so that neither it nor a later first compiled call runs the
    ``scipy.linalg`` package."""
    if "numba.np.arraymath" in sys.modules:
        return
    with blas_probe_alone():
        import_module("numba.np.arraymath")


@contextlib.contextmanager
def lazy_modules(names: tuple[str, ...]):
    """Inside the block, an import of one of ``names`` (not loaded yet) binds the module
    without running it: it runs, complete, on the first use of a name it defines (an
    attribute its module object lacks), whenever that is; its ``__spec__``, ``__name__``
    and the like are there from the start, so a second ``import`` of it does not run it
    (``importlib.util.LazyLoader`` runs a module on any attribute, ``__spec__`` included,
    which the import system reads on every import of a module already loaded). For
    modules a package imports only to have its classes defined: ``import prefect`` runs
    ``prefect.blocks``, whose ``notifications`` and ``webhook`` define some 20 pydantic
    block models (0.3-0.7 CPU-s) that a flow run never uses. Only the command's own process
    (``swathflow run``, ``demo``); a module already loaded is left as it is."""
    finder = _LazyFinder(names)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)


class _LazyFinder(importlib.abc.MetaPathFinder):
    def __init__(self, names):
        self.names = set(names)

    def find_spec(self, fullname, path, target=None):
        if fullname not in self.names:
            return None
        self.names.discard(fullname)           # the usual finders, without this one
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return None
        spec.loader = _Unrun(spec.loader)
        return spec


class _Unrun(importlib.abc.Loader):
    """Loads a module by giving it the class :class:`_UnrunModule` (its code not run)."""

    def __init__(self, loader):
        self.loader = loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module):
        module.__class__ = _UnrunModule


_UNRUN_LOCK = threading.RLock()


class _UnrunModule(type(sys)):          # types.ModuleType
    def __getattr__(self, name):
        """A name the module does not have yet: run its code (with its own loader, once,
        whichever thread asks first), then look the name up again."""
        with _UNRUN_LOCK:
            loader = self.__spec__.loader
            if isinstance(loader, _Unrun):
                self.__class__ = type(sys)
                self.__spec__.loader = self.__loader__ = loader.loader
                loader.loader.exec_module(self)
            elif type(self) is _UnrunModule:
                raise AttributeError(name)
        return getattr(self, name)
