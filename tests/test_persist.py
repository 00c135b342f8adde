"""Model and surrogate files that load without running code: exact round trips, and every way a
file can be refused (missing, not ours, another kind or version, an older pickle, tampered)."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import pickle
import struct
import zipfile

import numpy as np
import pytest

from crashfuse.cli import main
from crashfuse.errors import InputError
from crashfuse.gp.kriging import KrigingGP
from crashfuse.io import persist
from crashfuse.method.config import MethodConfig
from crashfuse.method.model import FORMAT, fit_model, load_model, load_surrogate, save_surrogate
from crashfuse.method.onset import OnsetCorrectedBias
from crashfuse.method.rollout import predict
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.world.generate import build
from crashfuse.world.presets import resolve

FAST = dict(n_grid=40, n_restarts=0)


@pytest.fixture(scope="module")
def campaign():
    return build(resolve("paper"), seed=0, n_cae=20)[0]


@pytest.fixture(scope="module")
def surrogate(campaign):
    return CAESurrogate(random_state=0).fit(campaign)


@pytest.fixture(scope="module")
def model(campaign, surrogate):
    """The richest model: state inputs, K = 2 pooled clusters, the onset correction (a partial)."""
    return fit_model(campaign, MethodConfig(k=2, inputs="state", **FAST), surrogate=surrogate)


@pytest.fixture()
def model_file(tmp_path, model):
    path = tmp_path / "model.cfmodel"
    model.save(path)
    return path


# ----------------------------------------------------------------------------- exact round trips
def same(a, b, path="obj"):
    """Assert ``a`` and ``b`` have the same types and the same bits, all the way down."""
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        if a.dtype == object:
            for i, (x, y) in enumerate(zip(a.ravel(), b.ravel())):
                same(x, y, f"{path}[{i}]")
        else:
            assert a.tobytes() == b.tobytes(), path
    elif isinstance(a, (float, np.floating)):
        assert struct.pack("<d", float(a)) == struct.pack("<d", float(b)) or math.isnan(a) and math.isnan(b), path
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, functools.partial):
        assert a.func is b.func, path
        same(a.args, b.args, f"{path}.args")
        same(a.keywords, b.keywords, f"{path}.keywords")
    elif hasattr(a, "__dict__") and not callable(a):
        derived = getattr(type(a), "_derived_attributes", ())  # rebuilt on first use: checked below
        same({k: v for k, v in vars(a).items() if k not in derived},
             {k: v for k, v in vars(b).items() if k not in derived}, f"{path}.__dict__")
    else:
        assert a == b, path


def _at(model, pulse, seed=3):
    return predict(model, pulse.v0, pulse.front_weight, pulse.rear_weight, pulse.meta["powertrain"],
                   pulse.meta["drive"], n_samples=30, random_state=seed)


def test_a_model_file_gives_back_every_fitted_value_and_the_same_predictions(campaign, model, model_file):
    loaded = load_model(model_file)
    assert isinstance(loaded.bias_["loading"], OnsetCorrectedBias)  # the partial, the pooled GP, two GMMs
    same(model, loaded)
    # Bit for bit as the model still in memory, not only as its pickle: a strided array in the
    # fitted model (once, the surrogate's PCA components) would take another BLAS path than its
    # contiguous copy in the file, and `--jobs 1` (in memory) and `--jobs 2` (pickled) would differ.
    for test_id in ("T02", "T08"):
        got, want = _at(loaded, campaign.pulses[test_id]), _at(model, campaign.pulses[test_id])
        for name in ("decel", "decel_lo", "decel_hi", "velocity", "cae_decel"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def _kriging_gps(obj, seen=None):
    """Every KrigingGP reachable from ``obj``."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return []
    seen.add(id(obj))
    if isinstance(obj, KrigingGP):
        return [obj]
    items = (obj.values() if isinstance(obj, dict) else obj if isinstance(obj, (list, tuple))
             else vars(obj).values() if hasattr(obj, "__dict__") and not callable(obj) else [])
    return [gp for x in items for gp in _kriging_gps(x, seen)]


def test_a_model_file_leaves_out_the_gp_factors_and_a_loaded_model_rebuilds_them_bit_for_bit(model, model_file):
    tree = json.loads(zipfile.ZipFile(model_file).read(persist.HEADER))["tree"]
    assert '"L_"' not in json.dumps(tree)
    want, got = _kriging_gps(model), _kriging_gps(load_model(model_file))
    assert len(want) == len(got) >= 5  # two pooled GPs, their cluster GPs, the onset GP
    for a, b in zip(want, got):
        assert "L_" not in vars(b)
        assert b.L_.tobytes() == a.L_.tobytes()


def test_a_surrogate_file_gives_back_the_same_curves(tmp_path, campaign, surrogate):
    save_surrogate(surrogate, tmp_path / "s.cfmodel")
    loaded = load_surrogate(tmp_path / "s.cfmodel")
    same(surrogate, loaded)
    loaded.check_campaign(campaign)
    p = campaign.pulses["T04"]
    got = loaded.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
    want = surrogate.curve(p.v0, p.front_weight, p.rear_weight, p.meta["powertrain"], p.meta["drive"])
    for name in ("a_loading", "a_unloading", "u", "s_max"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_saving_the_same_model_twice_gives_the_same_bytes(tmp_path, model, model_file):
    model.save(tmp_path / "again.cfmodel")
    assert (tmp_path / "again.cfmodel").read_bytes() == model_file.read_bytes()


@dataclasses.dataclass(frozen=True)
class Point:
    x: float
    label: str


def scaled(factor, x):
    return factor * x


def test_every_kind_of_value_round_trips_exactly(tmp_path):
    shared = np.arange(6.0).reshape(2, 3)
    values = {
        "scalars": [None, True, False, 0, -(2**70), 1.5, -0.0, 5e-324, math.nan, math.inf, -math.inf, "µs ✓"],
        "containers": ([], (), {}, (1, [2, (3,)]), {"a": {"b": [1]}}),
        "other keys": {1.5: "f", 2: "i", None: "n", (1, "a"): "t", math.inf: "inf", True: "b"},
        "arrays": [np.array([1.0, np.nan, -np.inf], dtype=np.float32), np.arange(4, dtype=np.int16),
                   np.array([True, False]), np.array(["T01", "T10"]), np.array(2.5), np.empty((0, 3)),
                   np.asfortranarray(np.arange(6.0).reshape(2, 3)), np.arange(10.0)[::-3],
                   np.array(["T01", "T02", "T01"], dtype=object), np.array([None, 1.5, "a"], dtype=object)],
        "numpy scalars": [np.float64(np.nan), np.float32(0.1), np.int32(-7), np.uint8(255), np.bool_(True),
                          np.str_("T04")],
        "whitelisted": [Point(0.1, "p"), functools.partial(scaled, 2.0), functools.partial(scaled, x=np.ones(2))],
        "shared": (shared, shared),
    }
    persist.save(tmp_path / "v.zip", "values", 1, values, [Point, scaled])
    loaded = persist.load(tmp_path / "v.zip", "values", 1, [Point, scaled])
    same(values, loaded)
    assert loaded["shared"][0] is loaded["shared"][1]  # one member, one array, as in memory
    assert loaded["whitelisted"][1](3.0) == 6.0


@pytest.mark.parametrize("value, words", [
    ({1, 2}, "builtins.set: not in the whitelist"),
    (Point(1.0, "p"), "Point: not in the whitelist"),
    (print, "builtin_function_or_method: not in the whitelist"),
    (np.complex128(1 + 2j), "dtype complex128"),
])
def test_saving_a_value_outside_the_whitelist_names_its_type(tmp_path, value, words):
    with pytest.raises(TypeError, match=words):
        persist.save(tmp_path / "v.zip", "values", 1, {"x": [value]}, [])
    assert not (tmp_path / "v.zip").exists()


def test_saving_a_cycle_fails(tmp_path):
    loop = []
    loop.append(loop)
    with pytest.raises(TypeError, match="cycle"):
        persist.save(tmp_path / "v.zip", "values", 1, loop, [])


# ----------------------------------------------------------------------------- refused files
def rewrite(src, dst, header=None, members=None):
    """Copy the zip ``src`` to ``dst`` with its header and members edited, as a tamperer would."""
    with zipfile.ZipFile(src) as zf:
        content = {name: zf.read(name) for name in zf.namelist()}
    head = json.loads(content.pop("header.json"))
    if header:
        header(head)
    if members:
        members(content)
    with zipfile.ZipFile(dst, "w") as zf:
        zf.writestr("header.json", json.dumps(head))
        for name, data in content.items():
            zf.writestr(name, data)
    return dst


def _retype(tree, old, new):
    """The JSON tree with every class or function name ``old`` replaced by ``new``."""
    return json.loads(json.dumps(tree).replace(json.dumps(old), json.dumps(new)))


def _first_array(head):
    return next(iter(head["arrays"]))


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 1]) + data[at + 1:]


def _refused(path, *words, loader=load_model):
    with pytest.raises(InputError) as err:
        loader(path)
    assert err.value.file == str(path)
    for w in words:
        assert w in str(err.value), str(err.value)
    return err.value


def test_missing_unreadable_and_foreign_files_are_refused(tmp_path):
    _refused(tmp_path / "none.cfmodel", "no such model file")
    _refused(tmp_path, "cannot read the model file")  # a folder
    (tmp_path / "junk.cfmodel").write_bytes(b"time_s,decel_g\n0,1\n")
    _refused(tmp_path / "junk.cfmodel", "not a crashfuse model file", "zip")
    with zipfile.ZipFile(tmp_path / "bare.zip", "w") as zf:
        zf.writestr("a.npy", b"")
    _refused(tmp_path / "bare.zip", "no header.json")
    with zipfile.ZipFile(tmp_path / "text.zip", "w") as zf:
        zf.writestr("header.json", "{kind: model")
    _refused(tmp_path / "text.zip", "header.json is not JSON")
    with zipfile.ZipFile(tmp_path / "partial.zip", "w") as zf:
        zf.writestr("header.json", json.dumps({"kind": "model", "format": FORMAT["model"]}))
    _refused(tmp_path / "partial.zip", "lacks kind, format, arrays or tree")


def test_an_older_pickle_file_is_refused_without_being_opened(tmp_path):
    # Unpickled, this payload would run code (exec) at load; the refusal comes from the pickle's
    # first two bytes.
    class Boom:
        def __reduce__(self):
            return (exec, ("raise SystemExit('a pickle ran code')",))

    for kind, loader, refit in (("model", load_model, "crashfuse fit"),
                                ("surrogate", load_surrogate, "crashfuse prepare")):
        old = tmp_path / f"{kind}.pkl"
        old.write_bytes(pickle.dumps({"format": FORMAT[kind] - 1, kind: Boom()}, protocol=pickle.HIGHEST_PROTOCOL))
        _refused(old, f"an older crashfuse's pickle {kind} file, which is no longer read", refit, loader=loader)


def test_another_kind_or_format_version_is_refused(tmp_path, model, model_file):
    save_surrogate(model.surrogate, tmp_path / "s.cfmodel")
    _refused(tmp_path / "s.cfmodel", "a crashfuse surrogate file, expected a model file")
    _refused(model_file, "a crashfuse model file, expected a surrogate file", loader=load_surrogate)
    old = rewrite(model_file, tmp_path / "old.cfmodel", header=lambda h: h.update(format=FORMAT["model"] - 1))
    err = _refused(old, f"model file format {FORMAT['model'] - 1} (written by crashfuse",
                   f"this crashfuse reads {FORMAT['model']}: refit with `crashfuse fit`")
    assert err.field == "format"


@pytest.mark.parametrize("old, new", [
    ("crashfuse.gp.kriging.KrigingGP", "os.system"),  # an object of a class outside the whitelist
    ("crashfuse.method.projection.nominal_time", "builtins.eval"),  # the onset correction's partial
    ("crashfuse.method.model.FittedModel", "crashfuse.method.model.load_model"),  # ours, but not whitelisted
])
def test_a_name_outside_the_whitelist_is_refused(tmp_path, model_file, old, new):
    bad = rewrite(model_file, tmp_path / "bad.cfmodel", header=lambda h: h.update(tree=_retype(h["tree"], old, new)))
    err = _refused(bad, f"unknown type '{new}' in the object tree", "tampered or foreign file")
    assert err.field == "tree"


def test_a_malformed_tree_is_refused(tmp_path, model_file):
    def swap_node(h):
        h["tree"] = {"object": {"type": "crashfuse.method.model.FittedModel", "state": {"x": {"lambda": 1}}}}

    _refused(rewrite(model_file, tmp_path / "a.cfmodel", header=swap_node), "invalid object tree", "'lambda'")

    def dangling(h):
        h["tree"] = {"ndarray": "arrays/999.npy"}

    _refused(rewrite(model_file, tmp_path / "b.cfmodel", header=dangling), "names an array the header does not list")


def test_a_tampered_or_damaged_array_is_refused(tmp_path, model_file):
    with zipfile.ZipFile(model_file) as zf:
        name = _first_array(json.loads(zf.read("header.json")))
        data, offset = zf.read(name), zf.getinfo(name).header_offset
    # A consistent zip whose array changed: only the header's SHA-256 tells.
    edited = rewrite(model_file, tmp_path / "edited.cfmodel", members=lambda m: m.update({name: _flip(data, 200)}))
    _refused(edited, f"array member '{name}' does not match its SHA-256 in the header")
    # A byte flipped in place: the zip's own CRC-32 tells first.
    raw = model_file.read_bytes()
    at = raw.index(data, offset) + 200
    (tmp_path / "flipped.cfmodel").write_bytes(_flip(raw, at))
    _refused(tmp_path / "flipped.cfmodel", f"array member '{name}'", "damaged or tampered")
    missing = rewrite(model_file, tmp_path / "missing.cfmodel", members=lambda m: m.pop(name))
    _refused(missing, f"array member '{name}' is missing")
    extra = rewrite(model_file, tmp_path / "extra.cfmodel", members=lambda m: m.update({"run.py": b"print(1)"}))
    _refused(extra, "member 'run.py' is not listed in the header")


def test_a_pickled_array_is_refused_even_with_a_matching_checksum(tmp_path, model_file):
    """numpy reads the members with allow_pickle=False: an object array smuggled in as .npy fails."""
    import io

    buf = io.BytesIO()
    np.save(buf, np.array([print], dtype=object), allow_pickle=True)
    evil = buf.getvalue()
    with zipfile.ZipFile(model_file) as zf:
        name = _first_array(json.loads(zf.read("header.json")))

    def digest(h):
        h["arrays"][name] = hashlib.sha256(evil).hexdigest()

    bad = rewrite(model_file, tmp_path / "bad.cfmodel", header=digest, members=lambda m: m.update({name: evil}))
    _refused(bad, f"array member '{name}' is not a numpy array file")


def test_the_cli_exits_2_with_one_line_on_a_tampered_model_file(tmp_path, model_file, capsys):
    bad = rewrite(model_file, tmp_path / "bad.cfmodel",
                  header=lambda h: h.update(tree=_retype(h["tree"], "crashfuse.gp.kriging.KrigingGP", "os.system")))
    out = tmp_path / "pred.csv"
    argv = ["predict", str(bad), "--v0-mph", "25", "--front-weight-lb", "2000", "--rear-weight-lb", "1500",
            "--powertrain", "Type II", "--drive", "AWD", "--samples", "5", "--out", str(out)]
    capsys.readouterr()
    assert main(argv) == 2
    stdout, stderr = capsys.readouterr()
    lines = stderr.strip().splitlines()
    assert stdout == "" and len(lines) == 1 and "Traceback" not in stderr
    assert lines[0].startswith("crashfuse: error: ") and str(bad) in lines[0] and "unknown type 'os.system'" in lines[0]
    assert not out.exists()
