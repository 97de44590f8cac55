r"""Keys that name a program without tracing it, and the small disk store they index.

A fresh process that finds a compiled kernel on disk should not have to trace the program to
find it: the trace (and the checks made before it) costs more than loading the kernel. The
program a member's function traces to is determined by

- the code of every Python function it calls, the values its closures, defaults and the
  module globals it reads hold (found by walking the functions' code objects), and the
  static configuration (options, steppers, tree structures) — `fingerprint`;
- the library's own source, the versions of Python, JAX, jaxlib and NumPy, and JAX's options
  that change a trace (64-bit types, promotion rules, matmul precision) — `environment`;
- the arguments' tree structure, shapes and dtypes (the caller adds them).

`fingerprint(obj)` is a hex digest of those, or None when `obj` holds something whose effect on
a trace cannot be read this way (a tracer, an object of a class defined outside the trusted
libraries, a module that is not one of them read by attribute): the caller then traces, as
before. A changed function body, closure constant, default or global value gives another key,
so a stale kernel is never found under it. The functions of the trusted libraries (this
package, JAX, NumPy) are named by module and qualified name plus their code, closures and
defaults; their module globals are covered by the source digest and the versions.
`cache_dir`, `read` and `write` keep small records (and the kernels' object code,
`clebsch_jax.native.kernel`) under such keys.
"""

from __future__ import annotations

import builtins
import dataclasses
import enum
import functools
import hashlib
import os
import sys
import threading
import types

import numpy as np

__all__ = ["fingerprint", "environment", "values_digest", "record_key", "cache_dir", "read", "write"]

TRUSTED = ("clebsch_jax", "jax", "jaxlib", "numpy", "math", "builtins", "functools", "operator", "ml_dtypes")
"""Top-level modules whose functions and classes are named, not walked: their source is this
package's (in `environment`'s digest) or fixed by a version in it, or the standard library's."""


class _Unknown(Exception):
    """An object whose effect on a trace `fingerprint` cannot read."""


def _trusted(module: str | None) -> bool:
    return module is not None and module.split(".")[0] in TRUSTED


def _named(obj) -> str:
    module, name = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if not (_trusted(module) and name):
        raise _Unknown(obj)
    return f"{module}:{name}"


class _Walk:
    """One fingerprint: the parts fed to a hash, objects already seen named by their order."""

    def __init__(self):
        self.h = hashlib.sha256()
        self.seen: dict = {}

    def put(self, *parts) -> None:
        for p in parts:
            self.h.update(str(p).encode())
            self.h.update(b"\x1f")

    def obj(self, x) -> None:  # noqa: C901 (one case per kind of object)
        if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
            self.put(type(x).__name__, repr(x))
            return
        if isinstance(x, (np.dtype, np.generic)):
            self.put(type(x).__name__, x.dtype if isinstance(x, np.generic) else "", repr(x))
            return
        if id(x) in self.seen:  # a cycle or a shared object: its first place
            self.put("ref", self.seen[id(x)][0])
            return
        self.seen[id(x)] = (len(self.seen), x)  # x kept alive, so that its id is not reused
        if isinstance(x, np.ndarray) or _is_concrete_jax_array(x):
            a = np.asarray(x)
            if a.dtype == object:
                raise _Unknown(x)
            self.put("array", a.dtype, a.shape)
            self.h.update(np.ascontiguousarray(a).tobytes())
            return
        if isinstance(x, enum.Enum):
            self.put("enum", _named(type(x)), x.name)
            return
        if isinstance(x, types.ModuleType):
            if not _trusted(x.__name__):
                raise _Unknown(x)
            self.put("module", x.__name__)
            return
        if isinstance(x, type):
            self.put("type", _named(x))
            return
        if isinstance(x, types.FunctionType):
            self.function(x)
            return
        if isinstance(x, types.MethodType):
            self.put("method")
            self.obj(x.__func__)
            self.obj(x.__self__)
            return
        if isinstance(x, functools.partial):
            self.put("partial", _named(type(x)))
            self.obj(x.func)
            self.obj(x.args)
            self.obj(x.keywords)
            return
        if isinstance(x, (tuple, list)):
            kind = type(x)
            self.put("seq", kind.__name__ if kind in (tuple, list) else _named(kind), len(x))
            for item in x:
                self.obj(item)
            return
        if isinstance(x, dict):
            self.put("dict", type(x).__name__ if type(x) is dict else _named(type(x)), len(x))
            for k, v in x.items():
                self.obj(k)
                self.obj(v)
            return
        if isinstance(x, (set, frozenset)):
            parts = sorted(fingerprint_or_raise(item) for item in x)
            self.put("set", type(x).__name__, *parts)
            return
        if type(x).__name__ == "PyTreeDef" and _trusted(type(x).__module__):
            self.treedef(x)
            return
        if isinstance(x, np.ufunc):
            self.put("ufunc", x.__name__)
            return
        if isinstance(x, types.BuiltinFunctionType) or callable(x) and not hasattr(x, "__dict__"):
            self.put("builtin", _named(x))  # C functions of the trusted libraries
            return
        if dataclasses.is_dataclass(x) and _trusted(type(x).__module__):
            self.put("dataclass", _named(type(x)))
            for f in dataclasses.fields(x):
                self.put(f.name)
                self.obj(getattr(x, f.name))
            return
        wrapped = getattr(x, "__wrapped__", None)
        if wrapped is not None:  # a library's function under jax.jit (jnp.sin): its options are the library's
            if not _trusted(getattr(wrapped, "__module__", None)):
                raise _Unknown(x)  # a user's jax.jit: its options (inline, static arguments) are not read here
            self.put("wrapper", _named(type(x)))
            self.obj(wrapped)
            return
        if _trusted(type(x).__module__) and hasattr(x, "__dict__"):  # e.g. jax.custom_jvp, library objects
            self.put("object", _named(type(x)))
            self.obj(dict(vars(x)))
            return
        raise _Unknown(x)

    def treedef(self, t) -> None:
        data = t.node_data()
        if data is None:
            self.put("leaf")
            return
        kind, aux = data
        children = t.children()
        self.put("node", kind.__name__ if kind in (tuple, list, dict) else _named(kind), len(children))
        self.obj(aux)
        for c in children:
            self.treedef(c)

    def function(self, f: types.FunctionType) -> None:
        self.put("function", getattr(f, "__module__", None), f.__qualname__)
        self.code(f.__code__)
        self.obj(f.__defaults__)
        self.obj(f.__kwdefaults__)
        cells = f.__closure__ or ()
        self.put("closure", len(cells))
        for c in cells:
            try:
                self.obj(c.cell_contents)
            except ValueError:  # an empty cell (a name assigned after the function was made)
                self.put("empty")
        if _trusted(getattr(f, "__module__", None)):
            return  # the module's globals: its source (in `environment`) or its version
        g = f.__globals__
        for name in sorted(_names(f.__code__)):
            if name in g:
                self.put("global", name)
                self.obj(g[name])
            elif not hasattr(builtins, name):
                self.put("unbound", name)  # an attribute's name, or a global not yet defined

    def code(self, c: types.CodeType) -> None:
        self.put(
            "code", c.co_argcount, c.co_posonlyargcount, c.co_kwonlyargcount, c.co_flags, c.co_names, c.co_varnames
        )
        self.put(c.co_freevars, c.co_cellvars)
        self.h.update(c.co_code)
        self.h.update(getattr(c, "co_exceptiontable", b""))  # Python 3.11+: where handlers start
        for k in c.co_consts:
            if isinstance(k, types.CodeType):
                self.code(k)
            else:
                self.obj(k)


def _names(code: types.CodeType) -> set:
    """The names a code object and the code nested in it read as globals or attributes."""
    found = set(code.co_names)
    for k in code.co_consts:
        if isinstance(k, types.CodeType):
            found |= _names(k)
    return found


def _is_concrete_jax_array(x) -> bool:
    jax = sys.modules.get("jax")
    if jax is None or not isinstance(x, jax.Array):
        return False
    if isinstance(x, jax.core.Tracer):
        raise _Unknown(x)
    return True


def fingerprint_or_raise(obj) -> str:
    w = _Walk()
    w.obj(obj)
    return w.h.hexdigest()


def fingerprint(obj) -> str | None:
    """A hex digest of what `obj` contributes to a trace (functions by their code, closures,
    defaults and globals; values by their bytes), or None where that cannot be read."""
    try:
        return fingerprint_or_raise(obj)
    except (_Unknown, RecursionError):
        return None


def stored_entries(a: np.ndarray) -> tuple:
    """`(axes, view)`: the axes along which `a` repeats its entries (a broadcast view,
    `np.broadcast_to`: stride 0 and length > 1) and `a` cut to one entry along them, a view of
    the entries it stores. Whatever holds for every entry of the view holds for every entry of
    `a`."""
    repeated = tuple(k for k, (n, stride) in enumerate(zip(a.shape, a.strides)) if n > 1 and stride == 0)
    if not repeated:
        return repeated, a
    return repeated, a[tuple(slice(0, 1) if k in repeated else slice(None) for k in range(a.ndim))]


def values_digest(tree) -> str:
    """A hex digest of the leaves of a pytree of concrete arrays: dtypes, shapes and bytes. Equal
    digests mean equal values; a broadcast view and a copy of it have different ones."""
    import jax

    h = hashlib.sha256()
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h.update(str(len(leaves)).encode())
    for x in leaves:
        a = np.asarray(x)
        h.update(f"{a.dtype}{a.shape}".encode())
        # a broadcast view by the entries it repeats and those axes: the same values, without
        # copying and hashing the repeats
        repeated, a = stored_entries(a)
        if repeated:
            h.update(f"repeated along {repeated}".encode())
        h.update(np.ascontiguousarray(a).data)  # the bytes, without a copy of them (tobytes)
    return h.hexdigest()


def record_key(*parts: str) -> str:
    """The key of a record made of `parts` (fingerprints, digests, names) in this environment."""
    h = hashlib.sha256()
    for p in (*parts, environment()):
        h.update(p.encode())
        h.update(b"\x1f")
    return h.hexdigest()


_ENV: list = []
_ENV_LOCK = threading.Lock()
_CONFIG = (
    "jax_enable_x64",
    "jax_numpy_rank_promotion",
    "jax_numpy_dtype_promotion",
    "jax_default_matmul_precision",
    "jax_default_prng_impl",
    "jax_enable_checks",
)


def environment() -> str:
    """A hex digest of what every trace depends on besides its own functions and arguments:
    the source of this package, the versions of Python, JAX, jaxlib and NumPy, and JAX's
    options that change a trace."""
    import jax
    import jaxlib

    with _ENV_LOCK:
        if not _ENV:
            h = hashlib.sha256()
            root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
            for folder, _, files in sorted(os.walk(root)):
                for name in sorted(files):
                    if name.endswith(".py"):
                        h.update(os.path.relpath(os.path.join(folder, name), root).encode())
                        with open(os.path.join(folder, name), "rb") as f:
                            h.update(f.read())
            h.update(f"{sys.version}|{jax.__version__}|{jaxlib.__version__}|{np.__version__}".encode())
            _ENV.append(h.hexdigest())
        source = _ENV[0]
    options = tuple(getattr(jax.config, name, None) for name in _CONFIG)
    found = _ENV_OPTIONS.get(options)
    if found is None:
        found = hashlib.sha256(f"{source}|{options!r}".encode()).hexdigest()
        _ENV_OPTIONS[options] = found
    return found


_ENV_OPTIONS: dict = {}


def cache_dir() -> str:
    """Where compiled kernels and the records that name them are kept:
    `$CLEBSCH_JAX_NATIVE_CACHE`, else `~/.cache/clebsch-jax/native` (`$XDG_CACHE_HOME` honoured)."""
    path = os.environ.get("CLEBSCH_JAX_NATIVE_CACHE")
    if path:
        return path
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "clebsch-jax", "native")


def _path(key: str, suffix: str) -> str:
    return os.path.join(cache_dir(), key[:2], key + suffix)


def read(key: str, suffix: str) -> bytes | None:
    """The record of `key` (a hex digest) with this suffix, or None."""
    try:
        with open(_path(key, suffix), "rb") as f:
            return f.read()
    except OSError:
        return None


def write(key: str, suffix: str, data: bytes) -> None:
    """Keep `data` under `key`; atomic (a reader sees the whole record or none). A cache that
    cannot be written only costs the next process the work again."""
    path = _path(key, suffix)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.{threading.get_ident()}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError:
        pass
