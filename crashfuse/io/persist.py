"""Object files that load without running code: a zip of a JSON header and ``.npy`` arrays.

A pickle runs whatever code it names when it is opened. These files hold data only:

* ``header.json``: ``kind`` and ``format`` (what the file is, which version of its layout),
  ``crashfuse`` (the version that wrote it), ``arrays`` (member name -> SHA-256 of its bytes) and
  ``tree``, the object as JSON;
* ``arrays/<i>.npy``: the numeric arrays, read with ``allow_pickle=False``.

The tree is plain JSON for None, bool, int, str, finite float and list; every other value is a
one-key object naming its type::

    {"float": "nan"}                       non-finite floats ("nan", "inf", "-inf")
    {"tuple": [...]}
    {"dict": {"k": ...}}                   string keys
    {"dict_items": [[k, v], ...]}          any other keys
    {"ndarray": "arrays/3.npy"}            the same array object twice: the same member
    {"object_array": {"shape": [...], "items": [...]}}   dtype object, items in C order
    {"scalar": {"dtype": "<f8", "value": ...}}            numpy bool, integer, float, str
    {"object": {"type": "pkg.mod.Class", "state": {...}}}
    {"function": "pkg.mod.name"}
    {"partial": {"func": ..., "args": [...], "keywords": {...}}}

Classes and functions are looked up by name in the ``types`` the caller passes (a whitelist):
the loader imports nothing and calls no code of the file's choosing; an instance is rebuilt with
``cls.__new__(cls)`` and its ``__dict__`` (no ``__init__``, no ``__setstate__``). Attributes a class
names in ``_derived_attributes`` are left out (e.g. a Cholesky factor: most of a model's bytes, and
cheaper to recompute than to write and read); the class rebuilds them on first use. Saving an object
whose type is not in the whitelist is a ``TypeError`` (extend the whitelist); loading a name
outside it is an :class:`~crashfuse.errors.InputError` (a tampered or foreign file).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import math
import os
import re
import zipfile
from typing import Iterable

import numpy as np

import crashfuse
from crashfuse.errors import InputError
from crashfuse.io.atomic import atomic_path

HEADER = "header.json"
_PICKLE_PROTOCOLS = range(2, 6)  # a pickle of protocol 2+ starts with b"\x80" and its protocol byte
_SCALAR_DTYPE = re.compile(r"[<>|=][biufU][0-9]+")  # numpy scalars the tree holds: bool, int, float, str
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed member times: the same object gives the same bytes


def save(path: str | os.PathLike, kind: str, version: int, obj, types: Iterable) -> None:
    """Write ``obj`` to ``path`` atomically.

    Parameters
    ----------
    path : str or PathLike
    kind : str
        What the file holds (e.g. ``"model"``); :func:`load` refuses another kind.
    version : int
        Format version of that kind; :func:`load` refuses another.
    obj : object
        Built from the types listed in the module docstring and instances of ``types``.
    types : iterable of classes and functions
        The whitelist (see :func:`encode`).

    Raises
    ------
    TypeError
        A value in ``obj`` of a type neither built in nor in ``types``, or a cycle.
    """
    tree, arrays = encode(obj, types)
    members = {f"arrays/{i}.npy": _npy_bytes(a) for i, a in enumerate(arrays)}
    header = {"kind": kind, "format": version, "crashfuse": crashfuse.__version__,
              "arrays": {name: hashlib.sha256(data).hexdigest() for name, data in members.items()}, "tree": tree}
    members[HEADER] = json.dumps(header, allow_nan=False, separators=(",", ":")).encode()
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members.items():
            zf.writestr(zipfile.ZipInfo(name, _ZIP_TIME), data)


def load(path: str | os.PathLike, kind: str, version: int, types: Iterable, refit: str = "refit"):
    """Read an object written by :func:`save`, without running code from the file.

    Parameters
    ----------
    path : str or PathLike
    kind : str
        The kind expected in the header.
    version : int
        The format version expected.
    types : iterable of classes and functions
        The whitelist: every class or function named in the file must be one of these.
    refit : str
        How to make a current file, for the messages on older files.

    Returns
    -------
    object

    Raises
    ------
    InputError
        Naming ``path``: missing or unreadable file, an older pickle file, not a zip archive, a
        missing or invalid header, another kind or format version, a name outside ``types``, an
        array member missing or not matching its SHA-256.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(2)
    except FileNotFoundError:
        raise InputError(f"no such {kind} file", path) from None
    except OSError as err:
        raise InputError(f"cannot read the {kind} file ({err.strerror})", path) from None
    if len(head) == 2 and head[0] == 0x80 and head[1] in _PICKLE_PROTOCOLS:
        raise InputError(f"an older crashfuse's pickle {kind} file, which is no longer read (opening a pickle can "
                         f"run any code it holds): {refit}", path)
    try:
        with zipfile.ZipFile(path) as zf:
            header = _header(zf, kind, version, refit)
            arrays = _arrays(zf, header["arrays"])
        return decode(header["tree"], arrays, types)
    except zipfile.BadZipFile as err:
        raise InputError(f"not a crashfuse {kind} file (not a readable zip archive: {err})", path) from None
    except OSError as err:
        raise InputError(f"cannot read the {kind} file ({err.strerror or err})", path) from None
    except InputError as err:
        raise err.at(path) from None


def encode(obj, types: Iterable) -> tuple[object, list[np.ndarray]]:
    """The JSON tree of ``obj`` and the arrays its ``ndarray`` nodes number.

    Parameters
    ----------
    obj : object
    types : iterable of classes and functions
        Classes whose instances may appear (state: their ``__dict__``) and functions that may
        appear, alone or in a ``functools.partial``; named ``module.qualname``.

    Returns
    -------
    tree : JSON-serialisable object
    arrays : list of ndarray
        ``arrays[i]`` is member ``arrays/<i>.npy``.

    Raises
    ------
    TypeError
        A value of a type neither built in nor in ``types``, or a cycle.
    """
    return _Encoder(types).run(obj)


def decode(tree, arrays: dict[str, np.ndarray], types: Iterable):
    """The object of a tree made by :func:`encode`.

    Parameters
    ----------
    tree : JSON object
    arrays : dict of str to ndarray
        By member name (``arrays/<i>.npy``).
    types : iterable of classes and functions
        The whitelist.

    Raises
    ------
    InputError
        A malformed tree, or a class or function name outside ``types`` (field ``tree``).
    """
    try:
        return _Decoder(types, arrays).value(tree)
    except RecursionError:
        raise InputError("the object tree nests too deep", field="tree") from None


def _names(types: Iterable) -> dict:
    return {f"{t.__module__}.{t.__qualname__}": t for t in types}


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


class _Encoder:
    def __init__(self, types: Iterable):
        self.names = {t: name for name, t in _names(types).items()}
        self.arrays: list[np.ndarray] = []
        self.members: dict[int, str] = {}  # id of an array already stored -> its member
        self.open: set[int] = set()  # containers being encoded: a second visit is a cycle

    def run(self, obj):
        return self.value(obj), self.arrays

    def value(self, o):
        t = type(o)
        if o is None or t in (bool, int, str):
            return o
        if t is float:
            return o if math.isfinite(o) else {"float": repr(o)}
        if t is np.ndarray:
            return self.ndarray(o)
        if isinstance(o, np.generic):
            return self.scalar(o)
        if t in (list, tuple, dict, functools.partial) or t in self.names:
            return self.container(o)
        if _hashable(o) and o in self.names:
            if isinstance(o, type):
                raise TypeError(f"cannot store the class {self.names[o]} itself, only its instances")
            return {"function": self.names[o]}
        raise TypeError(f"cannot store a {t.__module__}.{t.__qualname__}: not in the whitelist of stored types")

    def container(self, o):
        if id(o) in self.open:
            raise TypeError(f"cannot store a cycle (through a {type(o).__qualname__})")
        self.open.add(id(o))
        try:
            return self._container(o)
        finally:
            self.open.discard(id(o))

    def _container(self, o):
        t = type(o)
        if t is list:
            return [self.value(x) for x in o]
        if t is tuple:
            return {"tuple": [self.value(x) for x in o]}
        if t is dict:
            if all(type(k) is str for k in o):
                return {"dict": {k: self.value(v) for k, v in o.items()}}
            return {"dict_items": [[self.value(k), self.value(v)] for k, v in o.items()]}
        if t is functools.partial:
            if vars(o):
                raise TypeError("cannot store a functools.partial with attributes")
            return {"partial": {"func": self.value(o.func), "args": [self.value(x) for x in o.args],
                                "keywords": self.value(dict(o.keywords))["dict"]}}
        state = getattr(o, "__dict__", None)
        if type(state) is not dict or hasattr(t, "__slots__"):
            raise TypeError(f"cannot store a {self.names[t]}: its state is not only its __dict__")
        derived = getattr(t, "_derived_attributes", ())
        state = {k: v for k, v in state.items() if k not in derived}
        return {"object": {"type": self.names[t], "state": self.value(state)["dict"]}}

    def ndarray(self, a: np.ndarray):
        if a.dtype.hasobject:
            if a.dtype != object:
                raise TypeError(f"cannot store an array of dtype {a.dtype}")
            return {"object_array": {"shape": list(a.shape), "items": [self.value(x) for x in a.ravel()]}}
        if id(a) not in self.members:
            self.members[id(a)] = f"arrays/{len(self.arrays)}.npy"
            self.arrays.append(a)  # keeps ``a`` alive, so its id is not reused
        return {"ndarray": self.members[id(a)]}

    @staticmethod
    def scalar(x: np.generic):
        dtype = x.dtype.str
        if not _SCALAR_DTYPE.fullmatch(dtype) or x.dtype.kind == "f" and x.dtype.itemsize > 8:
            raise TypeError(f"cannot store a numpy scalar of dtype {x.dtype}")
        value = x.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = {"float": repr(value)}
        return {"scalar": {"dtype": dtype, "value": value}}


def _hashable(o) -> bool:
    try:
        hash(o)
    except TypeError:
        return False
    return True


_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


class _Decoder:
    def __init__(self, types: Iterable, arrays: dict[str, np.ndarray]):
        self.names = _names(types)
        self.arrays = arrays

    def value(self, node):
        if node is None or type(node) in (bool, int, float, str):
            return node
        if type(node) is list:
            return [self.value(x) for x in node]
        if type(node) is not dict or len(node) != 1:
            raise _invalid(f"expected a value, got {_short(node)}")
        (tag, body), = node.items()
        handler = getattr(self, f"tag_{tag}", None)
        if handler is None:
            raise _invalid(f"unknown node {tag!r}")
        return handler(body)

    def tag_float(self, body):
        if body not in _FLOATS:
            raise _invalid(f"expected 'nan', 'inf' or '-inf', got {_short(body)}")
        return _FLOATS[body]

    def tag_tuple(self, body):
        return tuple(self.value(x) for x in _of(body, list))

    def tag_dict(self, body):
        return {k: self.value(v) for k, v in _of(body, dict).items()}

    def tag_dict_items(self, body):
        out = {}
        for item in _of(body, list):
            if type(item) is not list or len(item) != 2:
                raise _invalid(f"expected a [key, value] pair, got {_short(item)}")
            key = self.value(item[0])
            if not _hashable(key):
                raise _invalid(f"an unhashable dict key {_short(item[0])}")
            out[key] = self.value(item[1])
        return out

    def tag_ndarray(self, body):
        if type(body) is not str or body not in self.arrays:
            raise _invalid(f"the tree names an array the header does not list: {_short(body)}")
        return self.arrays[body]

    def tag_object_array(self, body):
        shape, items = _of(body, dict).get("shape"), body.get("items")
        if type(shape) is not list or not all(type(n) is int and n >= 0 for n in shape) or type(items) is not list \
                or math.prod(shape) != len(items):
            raise _invalid("an object array whose shape does not match its items")
        out = np.empty(len(items), dtype=object)
        out[:] = [self.value(x) for x in items]  # element-wise: items that are sequences stay objects
        return out.reshape(shape)

    def tag_scalar(self, body):
        dtype, value = _of(body, dict).get("dtype"), body.get("value")
        if type(dtype) is not str or not _SCALAR_DTYPE.fullmatch(dtype):
            raise _invalid(f"a numpy scalar of dtype {_short(dtype)}")
        value = self.value(value)
        if type(value) not in (bool, int, float, str):
            raise _invalid(f"a numpy scalar of value {_short(value)}")
        try:
            return np.array(value, dtype=np.dtype(dtype))[()]
        except (OverflowError, ValueError) as err:
            raise _invalid(f"a numpy scalar {_short(value)} of dtype {dtype} ({err})") from None

    def tag_object(self, body):
        name, state = _of(body, dict).get("type"), body.get("state")
        cls = self._named(name)
        if not isinstance(cls, type):
            raise _invalid(f"{name} is not a class")
        obj = cls.__new__(cls)
        obj.__dict__.update(self.tag_dict(state))
        return obj

    def tag_function(self, body):
        func = self._named(body)
        if isinstance(func, type):
            raise _invalid(f"{body} is a class, not a function")
        return func

    def tag_partial(self, body):
        func, args, keywords = _of(body, dict).get("func"), body.get("args"), body.get("keywords")
        if type(func) is not dict or list(func) != ["function"]:
            raise _invalid(f"a functools.partial of {_short(func)}, expected a function")
        return functools.partial(self.tag_function(func["function"]), *self.value(_of(args, list)),
                                 **self.tag_dict(keywords))

    def _named(self, name):
        if type(name) is not str or name not in self.names:
            raise InputError(f"unknown type {_short(name)} in the object tree, outside the classes and functions "
                             f"this crashfuse reads: a tampered or foreign file, refused", field="tree")
        return self.names[name]


def _of(body, kind: type):
    if type(body) is not kind:
        raise _invalid(f"expected a JSON {'object' if kind is dict else 'array'}, got {_short(body)}")
    return body


def _short(node) -> str:
    text = json.dumps(node) if not isinstance(node, str) else repr(node)
    return text if len(text) <= 60 else text[:57] + "..."


def _invalid(message: str) -> InputError:
    return InputError(f"invalid object tree: {message}", field="tree")


def _header(zf: zipfile.ZipFile, kind: str, version: int, refit: str) -> dict:
    """The checked header: this kind and format, an array list matching the members."""
    try:
        header = json.loads(zf.read(HEADER))
    except KeyError:
        raise InputError(f"not a crashfuse {kind} file (no {HEADER} in the archive)") from None
    except (ValueError, RecursionError) as err:  # JSON or UTF-8
        raise InputError(f"not a crashfuse {kind} file ({HEADER} is not JSON: {err})", field=HEADER) from None
    if type(header) is not dict or not {"kind", "format", "arrays", "tree"} <= header.keys():
        raise InputError(f"not a crashfuse {kind} file ({HEADER} lacks kind, format, arrays or tree)", field=HEADER)
    if header["kind"] != kind:
        other = header["kind"] if type(header["kind"]) is str else _short(header["kind"])
        raise InputError(f"a crashfuse {other} file, expected a {kind} file", field="kind")
    if header["format"] != version or type(header["format"]) is not int:
        written = header.get("crashfuse")
        by = f" (written by crashfuse {written})" if type(written) is str else ""
        raise InputError(f"{kind} file format {_short(header['format'])}{by}, this crashfuse reads {version}: "
                         f"{refit}", field="format")
    sums = header["arrays"]
    if type(sums) is not dict or not all(type(v) is str for v in sums.values()):
        raise InputError(f"{HEADER}: expected 'arrays' to map member names to SHA-256 digests", field="arrays")
    extra = sorted(set(zf.namelist()) - set(sums) - {HEADER})
    if extra:
        raise InputError(f"member {extra[0]!r} is not listed in the header: a tampered or foreign file", field="arrays")
    return header


def _arrays(zf: zipfile.ZipFile, sums: dict[str, str]) -> dict[str, np.ndarray]:
    """Every listed array, each checked against its SHA-256 before numpy reads it."""
    out = {}
    for name, digest in sums.items():
        try:
            data = zf.read(name)
        except KeyError:
            raise InputError(f"array member {name!r} is missing: a damaged or tampered file", field="arrays") from None
        except zipfile.BadZipFile as err:  # the zip's own CRC-32 catches a flipped byte first
            raise InputError(f"array member {name!r} is damaged ({err}): a damaged or tampered file",
                             field="arrays") from None
        if hashlib.sha256(data).hexdigest() != digest:
            raise InputError(f"array member {name!r} does not match its SHA-256 in the header: a damaged or tampered "
                             f"file", field="arrays")
        try:
            out[name] = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, EOFError, SyntaxError) as err:
            raise InputError(f"array member {name!r} is not a numpy array file ({err})", field="arrays") from None
    return out
