"""Model files: exact round trips, no pickles, atomic writes, clear errors for bad files."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from test_tpsr import SMALL, structured_episodes

from tpsr_ros.core.errors import ModelFormatError
from tpsr_ros.core.pca_baseline import fit_pca
from tpsr_ros.core.tpsr import TPSRModel, fit_tpsr
from tpsr_ros.io import npz_archive
from tpsr_ros.io.model_io import FORMAT_VERSION, load_model, read_metadata, save_model


@pytest.fixture(scope="module")
def tpsr() -> TPSRModel:
    h, o, a, t = structured_episodes(200, seed=11)
    return fit_tpsr(h, o, a, t, n_actions=3, config=SMALL)


TRAINING = {"bags": [{"path": "bags/x", "steps": 600}], "steps": 600, "environment": "full"}


def test_metadata_without_nan(tmp_path, tpsr):
    training = {"gain": float("inf"), "offset": np.float64("nan"), "where": tmp_path}
    meta = read_metadata(save_model(tpsr, tmp_path / "m.npz", training=training))
    assert meta["training"] == {"gain": "inf", "offset": "nan", "where": str(tmp_path)}


def rewrite(src, dst, *, metadata=None, arrays=None, drop=()):
    """Copy a model file changing its metadata or arrays."""
    with np.load(src, allow_pickle=False) as npz:
        content = {k: npz[k] for k in npz.files if k not in drop}
    meta = json.loads(str(content["metadata"]))
    if metadata:
        meta.update(metadata)
    content["metadata"] = np.array(json.dumps(meta))
    content.update(arrays or {})
    with open(dst, "wb") as handle:
        np.savez(handle, **content)


def test_tpsr_round_trip_is_exact(tmp_path, tpsr):
    path = save_model(tpsr, tmp_path / "m.npz", training=TRAINING)
    again = load_model(path)
    assert isinstance(again, TPSRModel)
    assert again.config == tpsr.config
    for name, arr in tpsr.to_arrays().items():
        np.testing.assert_array_equal(again.to_arrays()[name], arr)
        assert again.to_arrays()[name].dtype == arr.dtype
    assert again.fit_info == json.loads(json.dumps(tpsr.fit_info))
    rng = np.random.default_rng(0)
    actions, obs = rng.integers(3, size=50), rng.standard_normal((50, 12))
    np.testing.assert_array_equal(again.track(actions, obs).states, tpsr.track(actions, obs).states)
    meta = read_metadata(path)
    assert meta["format_version"] == FORMAT_VERSION and meta["method"] == "tpsr"
    assert meta["parameters"] == tpsr.config.to_dict()
    assert meta["training"] == TRAINING
    assert meta["summary"]["singular_values"] == tpsr.singular_values.tolist()
    assert set(meta["summary"]["explained_variance"]) == {"obs", "history", "test"}
    assert "timings" in meta["summary"]


def test_pca_round_trip_is_exact(tmp_path):
    obs = np.random.default_rng(1).standard_normal((100, 6))
    model = fit_pca(obs, n_actions=25)
    again = load_model(save_model(model, tmp_path / "p.npz"))
    np.testing.assert_array_equal(
        again.track(np.zeros(100, int), obs).states, model.track(np.zeros(100, int), obs).states
    )
    assert again.method == "pca" and again.n_actions == 25


def test_file_holds_no_pickles(tmp_path, tpsr):
    path = save_model(tpsr, tmp_path / "m.npz")
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
    with np.load(path, allow_pickle=False) as npz:  # would raise on any object array
        assert sorted(f"{k}.npy" for k in npz.files) == sorted(names)
        dtypes = {k: npz[k].dtype for k in npz.files}
    assert dtypes.pop("metadata").kind == "U"
    assert all(dt == np.float64 for dt in dtypes.values()), dtypes


def test_refuses_to_overwrite_unless_forced(tmp_path, tpsr):
    path = save_model(tpsr, tmp_path / "m.npz")
    before = path.read_bytes()
    with pytest.raises(ModelFormatError, match="already exists; use --force"):
        save_model(tpsr, path)
    assert path.read_bytes() == before
    save_model(tpsr, path, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]  # no temporary files left


def test_nothing_is_written_on_failure(tmp_path, tpsr, monkeypatch):
    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        save_model(tpsr, tmp_path / "m.npz")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ModelFormatError, match="does not exist"):
        save_model(tpsr, tmp_path / "missing" / "m.npz")


def test_truncated_file(tmp_path, tpsr):
    data = save_model(tpsr, tmp_path / "m.npz").read_bytes()
    for cut in (10, len(data) // 2, len(data) - 30):
        bad = tmp_path / f"cut{cut}.npz"
        bad.write_bytes(data[:cut])
        with pytest.raises(ModelFormatError, match="truncated or foreign"):
            load_model(bad)


def test_foreign_files(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(ModelFormatError, match="truncated or foreign"):
        load_model(text)
    npy = tmp_path / "a.npy"
    np.save(npy, np.zeros(3))
    with pytest.raises(ModelFormatError, match="single array"):
        load_model(npy)
    other = tmp_path / "other.npz"
    np.savez(other, weights=np.zeros(3))
    with pytest.raises(ModelFormatError, match="no 'metadata' entry"):
        load_model(other)
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, metadata=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ModelFormatError):
        load_model(pickled)
    with pytest.raises(ModelFormatError, match="does not exist"):
        load_model(tmp_path / "nope.npz")


def test_other_format_version_names_both(tmp_path, tpsr):
    src = save_model(tpsr, tmp_path / "m.npz")
    rewrite(src, tmp_path / "v2.npz", metadata={"format_version": 2})
    with pytest.raises(ModelFormatError, match="version 2; this tpsr-ros reads version 1"):
        load_model(tmp_path / "v2.npz")
    rewrite(src, tmp_path / "f.npz", metadata={"format": "policy"})
    with pytest.raises(ModelFormatError, match="'policy' file"):
        load_model(tmp_path / "f.npz")
    rewrite(src, tmp_path / "m2.npz", metadata={"method": "lstm"})
    with pytest.raises(ModelFormatError, match="method 'lstm'"):
        load_model(tmp_path / "m2.npz")


def test_bad_arrays(tmp_path, tpsr):
    src = save_model(tpsr, tmp_path / "m.npz")
    cases = {
        "missing": ({"drop": ("b_inf",)}, "lacks the arrays \\['b_inf'\\]"),
        "shape": ({"arrays": {"b_inf": np.zeros(4)}}, "'b_inf' of .* has shape \\(4,\\)"),
        "dtype": ({"arrays": {"B": tpsr.B.astype(np.float32)}}, "dtype float32"),
        "nan": ({"arrays": {"b_star": np.full(3, np.nan)}}, "non-finite"),
        "extra": ({"arrays": {"extra": np.zeros(1)}}, "unexpected arrays \\['extra'\\]"),
        # shapes are checked against the metadata before any array is read
        "actions": ({"metadata": {"n_actions": 7}}, "'B' of .* its metadata implies \\(7, "),
        "params": ({"metadata": {"parameters": {"rank": -1}}}, "lacks a valid 'rank' entry"),
    }
    for name, (change, message) in cases.items():
        dst = tmp_path / f"{name}.npz"
        rewrite(src, dst, **change)
        with pytest.raises(ModelFormatError, match=message):
            load_model(dst)


def _write_members(dst, members):
    """A zip of raw ``name -> bytes`` members, deflated (what a hostile file may be)."""
    with zipfile.ZipFile(dst, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)


def _members(src):
    with zipfile.ZipFile(src) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _npy(array=None, header=None):
    buffer = io.BytesIO()
    if header is None:
        np.save(buffer, array)
    else:
        np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue()


def test_hostile_model_files_are_refused_before_any_array_is_inflated(tmp_path, tpsr, monkeypatch):
    src = save_model(tpsr, tmp_path / "m.npz")
    members = _members(src)
    meta = json.loads(str(np.load(io.BytesIO(members["metadata.npy"]))))
    # a header declaring 2**40 values over 800 bytes
    huge = {**members, "B.npy": _npy(header={"descr": "<f8", "fortran_order": False,
                                            "shape": (2**40,)}) + b"\0" * 800}
    _write_members(tmp_path / "huge.npz", huge)
    with pytest.raises(ModelFormatError, match=r"declares shape \(1099511627776,\)"):
        load_model(tmp_path / "huge.npz")
    # deflated zeros whose shape agrees with doctored metadata, over the size limit (lowered
    # here to 16 MiB so the test writes 43 MB, not the GBs a real bomb inflates to)
    monkeypatch.setattr(npz_archive, "MAX_ARRAY_BYTES", 2**24)
    centres = 200_000
    bomb_meta = {**meta, "parameters": {**meta["parameters"], "obs_centers": centres}}
    header = {"descr": "<f8", "fortran_order": False, "shape": (3, centres, 3, 3)}
    with zipfile.ZipFile(tmp_path / "bomb.npz", "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            if name == "B.npy":
                with z.open(name, "w", force_zip64=True) as handle:
                    handle.write(_npy(header=header))
                    zeros = bytes(2**24)
                    for _ in range(3 * centres * 9 * 8 // len(zeros)):
                        handle.write(zeros)
                    handle.write(bytes(3 * centres * 9 * 8 % len(zeros)))
            elif name == "metadata.npy":
                z.writestr(name, _npy(np.array(json.dumps(bomb_meta))))
            else:
                z.writestr(name, data)
    assert (tmp_path / "bomb.npz").stat().st_size < 1_000_000
    with pytest.raises(ModelFormatError, match="more than the 16777216 this tpsr-ros reads"):
        load_model(tmp_path / "bomb.npz")
    # metadata of the wrong types or nested absurdly deep
    cases = {
        "method": ({**meta, "method": ["tpsr"]}, "holds method \"\\['tpsr'\\]\""),
        "observation": ({**meta, "observation": [768]}, "valid 'observation' entry"),
        "rank": ({**meta, "parameters": {**meta["parameters"], "rank": "5"}}, "valid 'rank'"),
    }
    for name, (changed, message) in cases.items():
        _write_members(tmp_path / f"{name}.npz",
                       {**members, "metadata.npy": _npy(np.array(json.dumps(changed)))})
        with pytest.raises(ModelFormatError, match=message):
            load_model(tmp_path / f"{name}.npz")
    deep = "[" * 100_000 + "]" * 100_000
    _write_members(tmp_path / "deep.npz", {**members, "metadata.npy": _npy(np.array(deep))})
    with pytest.raises(ModelFormatError, match="nests deeper than 64 levels"):
        load_model(tmp_path / "deep.npz")
    # an object array is refused from its header, pickles are never loaded
    objects = {**members, "b_inf.npy": _npy(header={"descr": "|O", "fortran_order": False,
                                                   "shape": (3,)}) + b"\0" * 24}
    _write_members(tmp_path / "objects.npz", objects)
    with pytest.raises(ModelFormatError, match="has dtype object"):
        load_model(tmp_path / "objects.npz")


def test_a_directory_is_named_as_one(tmp_path):
    with pytest.raises(ModelFormatError, match="is a directory, not a file"):
        load_model(tmp_path)
