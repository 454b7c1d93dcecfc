"""The optimized copies open_session keeps (HANDMOCAP_ONNX_CACHE): made on a model's first
load, read on the next, the same outputs to the bit, never stale, a bad copy made again."""
from pathlib import Path

import numpy as np
import onnxruntime as ort

from handmocap.perception import onnx_models
from handmocap.perception.onnx_models import ONNX_CACHE_ENV, open_session

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "detnet_lite0_int8.onnx"


def _opened_files(monkeypatch) -> list[str]:
    """The files onnxruntime is asked to open from now on (the real sessions are made)."""
    opened, real = [], ort.InferenceSession

    def spy(path, *args, **kwargs):
        opened.append(Path(path).name)
        return real(path, *args, **kwargs)
    monkeypatch.setattr(ort, "InferenceSession", spy)
    return opened


def _read(session) -> list[np.ndarray]:
    x = np.random.default_rng(0).random((2, 3, 128, 128), np.float32)
    return session.run(None, {session.get_inputs()[0].name: x})


def test_a_model_s_optimized_copy_is_made_once_then_read_with_the_same_outputs(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv(ONNX_CACHE_ENV, str(cache))
    opened = _opened_files(monkeypatch)
    first = open_session(MODEL, "DetNet", "make")
    copies = sorted(p.name for p in cache.iterdir())
    assert len(copies) == 1 and copies[0].startswith("detnet_lite0_int8-"), copies    # no temp file left
    second = open_session(MODEL, "DetNet", "make")
    assert opened == [MODEL.name, copies[0]]                     # the second load read the copy
    for a, b in zip(_read(first), _read(second)):
        np.testing.assert_array_equal(a, b)
    assert second.get_modelmeta().custom_metadata_map == first.get_modelmeta().custom_metadata_map

    (cache / copies[0]).write_bytes(b"not a model")              # a copy gone bad: made again, the load works
    third = open_session(MODEL, "DetNet", "make")
    assert opened[2:] == [copies[0], MODEL.name]
    for a, b in zip(_read(first), _read(third)):
        np.testing.assert_array_equal(a, b)
    assert (cache / copies[0]).stat().st_size > 1000


def test_a_changed_model_file_never_reads_an_old_copy_and_none_keeps_no_copies(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv(ONNX_CACHE_ENV, str(cache))
    model = tmp_path / "detnet.onnx"
    model.write_bytes(MODEL.read_bytes())
    old = onnx_models.optimized_copy(model, ort)
    open_session(model, "DetNet", "make")
    assert old.is_file()
    import onnx
    proto = onnx.load(str(model))
    onnx.helper.set_model_props(proto, {"retrained": "yes"})   # the same name, other bytes
    onnx.save(proto, str(model))
    new = onnx_models.optimized_copy(model, ort)
    assert new != old and new.parent == old.parent
    assert open_session(model, "DetNet", "make").get_modelmeta().custom_metadata_map == {"retrained": "yes"}

    monkeypatch.setenv(ONNX_CACHE_ENV, "none")
    other = tmp_path / "cache_off"
    monkeypatch.setenv("XDG_CACHE_HOME", str(other))
    assert onnx_models.onnx_cache_dir() is None
    open_session(model, "DetNet", "make")
    assert not other.exists()


def test_the_cache_keeps_the_copies_used_last(tmp_path, monkeypatch):
    import os
    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setenv(ONNX_CACHE_ENV, str(cache))
    old = [cache / f"old{i}-0.onnx" for i in range(onnx_models.ONNX_CACHE_FILES + 5)]
    for i, p in enumerate(old):
        p.write_bytes(b"x")
        os.utime(p, (1000 + i, 1000 + i))
    open_session(MODEL, "DetNet", "make")
    left = {p.name for p in cache.glob("*.onnx")}
    assert len(left) == onnx_models.ONNX_CACHE_FILES and onnx_models.optimized_copy(MODEL, ort).name in left
    assert {p.name for p in old[-(onnx_models.ONNX_CACHE_FILES - 1):]} <= left     # the oldest went first
