import numpy as np
import pytest
import torch

from nbvh_core.fileformat import (MAGIC, NBVHFileError, component_bytes, load_nbvh, pack_codes, read_info,
                                  save_nbvh, unpack_codes)
from nbvh_core.pipeline import compress_mesh, preset
from nbvh_core.quantize import StorageConfig
from nbvh_core.render import orbit_cameras, render_neural


@pytest.fixture(scope="module")
def trained(sample_meshes, tmp_path_factory):
    out = {}
    for enc in ("hashgrid", "hashvqad"):
        path = tmp_path_factory.mktemp("models") / f"{enc}.nbvh"
        res = compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(encoding=enc), path,
                            evaluate_quality=False)
        out[enc] = (path, res)
    return out


@pytest.mark.parametrize("bits", [1, 2, 4, 8])
def test_pack_unpack_codes(bits):
    codes = np.random.default_rng(0).integers(0, 1 << bits, size=1001).astype(np.uint8)
    packed = pack_codes(codes, bits)
    assert len(packed) == -(-1001 * bits // 8)
    assert np.array_equal(unpack_codes(packed, bits, 1001), codes)


@pytest.mark.parametrize("enc", ["hashgrid", "hashvqad"])
def test_save_load_render_identical(trained, enc):
    path, res = trained[enc]
    loaded = load_nbvh(path)
    cam = orbit_cameras(3)[1]
    a = render_neural(res.model, cam, 40, 40)
    b = render_neural(loaded, cam, 40, 40)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.hit, b.hit)
    for p, q in zip(res.model.network.parameters(), loaded.network.parameters()):
        assert torch.equal(p, q)


@pytest.mark.parametrize("enc", ["hashgrid", "hashvqad"])
def test_file_size_equals_component_bytes(trained, enc):
    path, res = trained[enc]
    info = read_info(path)
    assert info.total_bytes == path.stat().st_size == sum(info.components.values()) == res.file_bytes
    sizes = res.model.stored_bytes(res.settings.storage())
    assert info.components["bvh"] == sizes["bvh"] == 24 + len(res.model.nodes) * 10  # 8-bit boxes, 16-bit links
    assert info.components["features"] == sizes["features"]
    assert info.components["network"] == sizes["network"]
    if enc == "hashvqad":
        assert info.components["index"] == sizes["index"]  # 4 bits per entry at t = 16
    assert info.components["header"] < 4096 and info.components["padding"] < 64


def test_float16_halves_the_tables(trained, tmp_path):
    path, res = trained["hashgrid"]
    half, full = tmp_path / "half.nbvh", tmp_path / "full.nbvh"
    save_nbvh(res.model, half, storage=StorageConfig(16, 16, 32))
    save_nbvh(res.model, full, storage=StorageConfig.float32())
    a, b = read_info(full).components, read_info(half).components
    assert b["features"] * 2 == a["features"] and b["network"] * 2 == a["network"]
    m = load_nbvh(half)
    assert torch.allclose(m.encoding.table, res.model.encoding.float_rows(), atol=1e-3)


def test_damaged_truncated_and_foreign_files_refused(trained, tmp_path):
    path, _ = trained["hashvqad"]
    data = path.read_bytes()
    cases = {
        "flipped.nbvh": data[:200] + bytes([data[200] ^ 0x40]) + data[201:],
        "truncated.nbvh": data[: len(data) // 2],
        "empty.nbvh": b"",
        "foreign.nbvh": b"\x89PNG\r\n\x1a\n" + b"\0" * 100,
        "future.nbvh": MAGIC + (9).to_bytes(2, "little") + data[10:],
    }
    messages = {"flipped.nbvh": "checksum", "truncated.nbvh": "checksum", "empty.nbvh": "too short",
                "foreign.nbvh": "not an .nbvh", "future.nbvh": "version 9"}
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(NBVHFileError, match=messages[name]):
            load_nbvh(p)
    with pytest.raises(NBVHFileError, match="cannot read"):
        load_nbvh(tmp_path / "missing.nbvh")


def test_failed_save_keeps_existing_file(trained, tmp_path, monkeypatch):
    path, res = trained["hashgrid"]
    target = tmp_path / "keep.nbvh"
    target.write_bytes(b"previous result")
    import nbvh_core.fileformat as ff

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ff.os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space"):
        save_nbvh(res.model, target)
    assert target.read_bytes() == b"previous result"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.nbvh"]


def test_component_bytes_of_encoded_data(trained):
    path, _ = trained["hashvqad"]
    comps = component_bytes(path.read_bytes())
    assert set(comps) == {"header", "bvh", "features", "index", "network", "padding", "checksum"}
