import numpy as np
import pytest
import torch

from nbvh_core.storage.container import MAGIC, pack_codes, unpack_codes
from nbvh_core.storage.fileformat import NBVHFileError, component_bytes, load_nbvh, read_info, save_nbvh
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.neural.quantize import StorageConfig
from nbvh_core.rendering.render import orbit_cameras, render_neural


@pytest.fixture(scope="module")
def trained(sample_meshes, tmp_path_factory):
    out = {}
    for enc in ("hashgrid", "hashvqad"):
        path = tmp_path_factory.mktemp("models") / f"{enc}.nbvh"
        res = compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(encoding=enc), path,
                            evaluate_quality=False)
        out[enc] = (path, res)
    return out


@pytest.mark.parametrize("bits", [1, 2, 3, 4, 5, 6, 7, 8])
def test_pack_unpack_codes(bits):
    codes = np.random.default_rng(0).integers(0, 1 << bits, size=1001).astype(np.uint8)
    packed = pack_codes(codes, bits)
    assert len(packed) == -(-1001 * bits // 8)
    assert np.array_equal(unpack_codes(packed, bits, 1001), codes)
    with pytest.raises(ValueError, match="fewer"):
        unpack_codes(packed[:-1], bits, 1001 + 8)


def test_packed_codes_keep_their_byte_layout():
    """Files written before 6-bit tables hold 1- and 4-bit codes least significant first within each byte; the one
    bit stream reads them the same, and at 6 bits four codes fill three bytes."""
    assert pack_codes(np.array([1, 2], np.uint8), 4) == bytes([0x21])
    assert pack_codes(np.array([1, 0, 1, 1, 0, 0, 0, 0, 1], np.uint8), 1) == bytes([0b1101, 1])
    assert pack_codes(np.array([63, 0, 0, 1], np.uint8), 6) == bytes([63, 0, 0b100])  # code 3 at stream bit 18
    with pytest.raises(ValueError, match="not supported"):
        pack_codes(np.zeros(3, np.uint8), 9)


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
    n = len(res.model.nodes)
    assert info.components["bvh"] == sizes["bvh"] == 24 + 6 * n + (n + 7) // 8  # 8-bit boxes, 1 bit of shape a node
    assert info.components["features"] == sizes["features"]
    assert info.components["network"] == sizes["network"]
    if enc == "hashvqad":
        assert info.components["index"] == sizes["index"]  # 4 bits per entry at t = 16
    assert info.components["header"] < 4096 and info.components["padding"] < 64


@pytest.mark.parametrize("enc", ["hashgrid", "hashvqad"])
def test_the_planned_bytes_are_the_written_tensors(trained, enc):
    """The planner sizes a model with the reader's shape table (`payload_bytes`): equal to the written file's tensor
    bytes, and to a shapes-only model's count at every storage precision."""
    import itertools
    from nbvh_core.geometry.bvh import NODE_DTYPE
    from nbvh_core.neural.model import NeuralBVH
    from nbvh_core.storage.layout import payload_bytes

    path, res = trained[enc]
    cfg, storage, n = res.model.cfg, res.settings.storage(), len(res.model.nodes)
    info = read_info(path)
    tensors = sum(v for k, v in info.components.items() if k not in ("header", "padding", "checksum"))
    assert payload_bytes(cfg, storage, n) == tensors
    for bits in itertools.product((4, 6, 8, 16, 32), (4, 8, 16, 32), (8, 32)):
        st = StorageConfig(*bits)
        with torch.device("meta"):
            shapes_only = NeuralBVH(np.zeros(n, NODE_DTYPE), cfg)
        assert payload_bytes(cfg, st, n) == sum(shapes_only.stored_bytes(st).values()), bits


def test_hashvqad_file_keeps_the_reachable_codes_and_full_index_files_still_load(trained, tmp_path, monkeypatch):
    """Format 2.2 stores the codes of the index entries a vertex can select (the tiny grid's dense coarse level
    reaches 17^3 of its 8,192); a 2.1 file, which stored all L x H, loads to the same model."""
    import nbvh_core.storage.container as container

    path, res = trained["hashvqad"]
    enc = res.model.encoding
    cfg, bits = enc.cfg, enc.code_bits()
    reach = enc.reachable_entries()
    assert reach[0] == 17 ** 3 < cfg.index_size
    assert read_info(path).components["index"] == (sum(reach) * bits + 7) // 8
    assert enc.codes.numel() == (sum(reach) * bits + 7) // 8  # held as stored: packed
    new = load_nbvh(path)
    assert torch.equal(new.encoding.codes, enc.codes)
    old = tmp_path / "full_index.nbvh"
    monkeypatch.setattr(container, "VERSION_MINOR", 1)  # as a 2.1 writer wrote it
    save_nbvh(res.model, old, storage=res.settings.storage())
    monkeypatch.undo()
    assert old.read_bytes()[8:12] == bytes([2, 0, 1, 0])
    assert read_info(old).components["index"] == (cfg.levels * cfg.index_size * bits + 7) // 8
    loaded = load_nbvh(old)
    assert torch.equal(loaded.encoding.codes, enc.codes)
    cam = orbit_cameras(3)[0]
    a, b = render_neural(new, cam, 32, 32), render_neural(loaded, cam, 32, 32)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.hit, b.hit)


def test_a_hashvqad_file_with_more_codes_than_payload_bytes_loads(sample_meshes, tmp_path):
    """Packed codes can outnumber the file's bytes (4 bits each): a small table and network with a large index
    (H = 1024 T) must still pass the reader's shape checks (a 200 s HashVQAD run at T=2^9 once failed them)."""
    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.neural.encodings import EncodingConfig
    from nbvh_core.neural.model import ModelConfig, NeuralBVH
    from nbvh_core.neural.networks import NetworkConfig

    torch.manual_seed(0)
    cfg = ModelConfig(EncodingConfig(kind="hashvqad", log2_table=4, levels=2, features=2, n_max=32,
                                     index_factor=1024), NetworkConfig(kind="mlp", k=2, hidden=0))
    model = NeuralBVH(build_bvh(sample_meshes["blob"], 15).nodes, cfg).eval()
    model.encoding.freeze()
    path = tmp_path / "many_codes.nbvh"
    save_nbvh(model, path, storage=StorageConfig(32, 32, 32))
    count = sum(model.encoding.reachable_entries())
    assert count > path.stat().st_size
    loaded = load_nbvh(path)
    assert torch.equal(loaded.encoding.codes, model.encoding.codes)


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
    import nbvh_core.storage.fileformat as ff

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


def test_quantize_rows_is_symmetric_per_row_and_exact_at_the_largest_weight():
    from nbvh_core.neural.quantize import dequantize_rows, quantize_rows

    w = np.random.default_rng(1).normal(size=(37, 53)).astype(np.float32) * np.linspace(0.01, 3, 37)[:, None]
    w[5] = 0.0  # a zero row
    codes, scale = quantize_rows(w)
    assert codes.dtype == np.int8 and scale.dtype == np.float16 and scale.shape == (37,)
    back = dequantize_rows(codes, scale).astype(np.float32)
    step = scale.astype(np.float32)[:, None]
    assert (np.abs(back - w) <= 0.5 * step + 2e-3 * np.abs(w) + 1e-8).all()  # half a step (+ float16 rounding)
    assert (np.abs(codes).max(axis=1)[np.arange(37) != 5] >= 126).all() and not codes[5].any()
    c2, s2 = quantize_rows(back)  # a held (dequantized) network re-quantizes to the same rows
    assert np.array_equal(c2, codes) and np.array_equal(s2, scale)


def test_int8_network_file_loads_as_stored_and_renders_like_its_float16_twin(sample_meshes, tmp_path):
    """network_bits 8 (format 2.1): the file stores int8 rows + float16 scales, the loaded model holds exactly
    them (resident = stored), renders what the in-memory model renders, and stays close to the same training
    with a float16 network."""
    import copy

    s = preset("tiny").with_overrides(steps=300, rays_per_step=2048, force=True)
    res16 = compress_mesh(sample_meshes["blob"], s, tmp_path / "w16.nbvh", evaluate_quality=False)
    model8 = copy.deepcopy(res16.model)
    model8.hold_network_int8()
    save_nbvh(model8, tmp_path / "w8.nbvh", storage=StorageConfig(8, 8, 8))
    info8, info16 = read_info(tmp_path / "w8.nbvh"), read_info(tmp_path / "w16.nbvh")
    linears = [m for m in model8.network.modules() if isinstance(m, torch.nn.Linear)]
    n_w = sum(m.in_features * m.out_features for m in linears)
    n_out = sum(m.out_features for m in linears)
    assert info8.components["network"] == n_w + 4 * n_out == model8.stored_bytes(StorageConfig(8, 8, 8))["network"]
    assert info16.components["network"] == 2 * (n_w + n_out)
    loaded = load_nbvh(tmp_path / "w8.nbvh")
    assert loaded.resident_bytes()["network"] == info8.components["network"]
    for (n, p), (_, q) in zip(model8.network.state_dict().items(), loaded.network.state_dict().items()):
        assert p.dtype == q.dtype and torch.equal(p, q), n
    cam = orbit_cameras(3)[1]
    a, b = render_neural(model8, cam, 48, 48), render_neural(loaded, cam, 48, 48)
    assert np.array_equal(a.image, b.image)
    c = render_neural(res16.model, cam, 48, 48)
    assert c.hit.sum() > 100
    assert (a.hit == c.hit).mean() > 0.98 and float(np.abs(a.image - c.image)[a.hit & c.hit].mean()) < 0.03
    # A model trained with network_bits 8 is finalized the same way (what the pipeline writes).
    res8 = compress_mesh(sample_meshes["blob"], s.with_overrides(steps=20, network_bits=8), tmp_path / "p8.nbvh",
                         evaluate_quality=False)
    assert next(res8.model.network.parameters()).dtype == torch.int8
    assert read_info(tmp_path / "p8.nbvh").components["network"] == n_w + 4 * n_out


def test_four_bit_rows_hold_seven_codes_a_side_and_training_sees_them_as_the_file_will():
    """network_bits 4: codes in [-7, 7], the largest weight of a row exact; the training's grid (torch) gives the
    file's rows bit for bit (numpy); the straight-through step puts the float weights back."""
    from nbvh_core.neural.quantize import dequantize_rows, quantize_rows
    from nbvh_core.training.network_quantization import NetworkQuantization, rows_on_grid

    w = np.random.default_rng(2).normal(size=(29, 41)).astype(np.float32) * np.linspace(0.01, 3, 29)[:, None]
    w[3] = 0.0
    codes, scale = quantize_rows(w, 4)
    assert codes.min() >= -7 and codes.max() <= 7
    assert (np.abs(codes).max(axis=1)[np.arange(29) != 3] == 7).all() and not codes[3].any()
    back = dequantize_rows(codes, scale).astype(np.float32)
    assert (np.abs(back - w) <= 0.5 * scale.astype(np.float32)[:, None] + 2e-3 * np.abs(w) + 1e-8).all()
    assert np.array_equal(rows_on_grid(torch.from_numpy(w), 4).numpy(), back)

    net = torch.nn.Sequential(torch.nn.Linear(41, 29), torch.nn.ReLU(), torch.nn.Linear(29, 5))
    before = [m.weight.detach().clone() for m in net if isinstance(m, torch.nn.Linear)]
    grid = NetworkQuantization(net, 4, start=0.75)
    assert not grid.before_step(0.5)  # not yet due: untouched
    assert grid.before_step(0.8)
    for m, w0 in zip([m for m in net if isinstance(m, torch.nn.Linear)], before):
        c, s = quantize_rows(w0.numpy(), 4)
        assert np.array_equal(m.weight.detach().numpy(), dequantize_rows(c, s).astype(np.float32))
    grid.after_backward()
    assert all(torch.equal(m.weight, w0) for m, w0 in zip([m for m in net if isinstance(m, torch.nn.Linear)], before))
    assert not NetworkQuantization(net, 8, start=0.0).before_step(1.0)  # 8 bits: rounded once, at the end


def test_four_bit_network_file_packs_two_codes_a_byte_and_loads_as_trained(sample_meshes, tmp_path):
    """A model trained with network_bits 4 (its end through the rows on the grid) is written with each layer's codes
    two to a byte (the exact bytes `stored_bytes` predicts) and loads holding the same codes and scales, rendering
    the same image as the in-memory model."""
    s = preset("tiny").with_overrides(steps=40, force=True, encoding="hashgrid", network_bits=4, table_bits=8)
    res = compress_mesh(sample_meshes["blob"], s, tmp_path / "w4.nbvh", evaluate_quality=False)
    linears = [m for m in res.model.network.modules() if isinstance(m, torch.nn.Linear)]
    packed = sum(-(-m.in_features * m.out_features // 2) for m in linears)
    n_out = sum(m.out_features for m in linears)
    info = read_info(tmp_path / "w4.nbvh")
    assert info.components["network"] == packed + 4 * n_out == res.model.stored_bytes(s.storage())["network"]
    loaded = load_nbvh(tmp_path / "w4.nbvh")
    for (n, p), (_, q) in zip(res.model.network.state_dict().items(), loaded.network.state_dict().items()):
        assert p.dtype == q.dtype and torch.equal(p, q), n
    assert all(int(m.weight.abs().max()) <= 7 for m in linears)
    cam = orbit_cameras(3)[1]
    assert np.array_equal(render_neural(res.model, cam, 40, 40).image, render_neural(loaded, cam, 40, 40).image)


def test_the_header_is_stored_compressed_and_a_crafted_one_is_refused_in_one_line(trained, tmp_path, monkeypatch):
    """Format 2.4 stores the header zlib-compressed (smaller than its JSON); a 2.3 file (plain JSON) still loads;
    a header that is not zlib data, inflates past the reader's limit or has bytes after it is refused in one line."""
    import json
    import struct
    import zlib

    from fuzzing import craft, split
    from nbvh_core.storage.container import MAX_HEADER_BYTES, PREFIX
    from nbvh_core.storage.fileformat import decode_nbvh

    path, _ = trained["hashgrid"]
    data = path.read_bytes()
    header, payload = split(data)
    hlen = PREFIX.unpack_from(data, 0)[3]
    assert hlen < 0.6 * len(json.dumps(header, separators=(",", ":")))
    import nbvh_core.storage.container as container

    path_24, res = tmp_path / "as_2_4.nbvh", trained["hashgrid"][1]
    monkeypatch.setattr(container, "VERSION_MINOR", 4)  # links and leaf ordinals, as 2.3 and 2.4 wrote them
    save_nbvh(res.model, path_24, storage=res.settings.storage())
    monkeypatch.undo()
    old = decode_nbvh(craft(*split(path_24.read_bytes()), minor=3))  # plain JSON, as 2.3 wrote it
    assert old.n_nodes == load_nbvh(path).n_nodes

    def with_raw_header(raw: bytes) -> bytes:
        raw += b"\0" * ((-(PREFIX.size + len(raw))) % 8)
        body = PREFIX.pack(MAGIC, 2, 4, len(raw)) + raw + payload
        return body + struct.pack("<I", zlib.crc32(body))

    bomb = zlib.compress(b"{" + b" " * (MAX_HEADER_BYTES + 10) + b"}", 9)
    cases = {"not zlib": json.dumps(header).encode(), "inflate": bomb,
             "after": zlib.compress(json.dumps(header).encode()) + b"\x01" * 3}
    for why, raw in cases.items():
        with pytest.raises(NBVHFileError) as err:
            decode_nbvh(with_raw_header(raw), "crafted.nbvh")
        assert "\n" not in str(err.value) and "crafted.nbvh" in str(err.value), why


def test_the_bvh_shape_is_one_bit_a_node_and_any_other_layout_keeps_its_links(sample_meshes, trained, tmp_path):
    """Format 2.5: a tree laid out as `layout_cut` lays it out (breadth first, padding node at 1 when the count is
    even) is stored as one bit per node and loads with the same links and leaf ordinals; a tree numbered otherwise
    keeps its links; shape bits that make no tree are refused in one line."""
    from fuzzing import craft, split
    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.neural.quantize import links_from_shape, shape_bits
    from nbvh_core.storage.fileformat import decode_nbvh

    for budget in (1, 2, 15, 64, 511):  # odd, padded (even), a single leaf
        nodes = build_bvh(sample_meshes["blob"], budget).nodes
        bits = shape_bits(nodes["left"], nodes["leaf"])
        assert bits is not None and len(bits) == len(nodes)
        left, leaf = links_from_shape(bits)
        assert np.array_equal(left, nodes["left"]) and np.array_equal(leaf, nodes["leaf"])
    path, res = trained["hashgrid"]
    header, payload = split(path.read_bytes())
    names = {t["name"]: t for t in header["tensors"]}
    assert "bvh.shape" in names and "bvh.left" not in names and names["bvh.shape"]["nbytes"] == (63 + 7) // 8
    loaded = load_nbvh(path)
    assert np.array_equal(loaded.nodes["left"], res.model.nodes["left"])
    assert np.array_equal(loaded.nodes["leaf"], res.model.nodes["leaf"])
    # Leaf ordinals numbered backwards: a valid tree, not the builder's layout: stored with its links, read back.
    model = load_nbvh(path)
    nodes = model.nodes.copy()
    is_leaf = nodes["leaf"] >= 0
    nodes["leaf"][is_leaf] = is_leaf.sum() - 1 - nodes["leaf"][is_leaf]
    model.set_nodes(nodes)
    assert shape_bits(nodes["left"], nodes["leaf"]) is None and not model.shape_only()
    other = tmp_path / "reordered.nbvh"
    save_nbvh(model, other, storage=res.settings.storage())
    assert {"bvh.left", "bvh.leaf"} <= {t["name"] for t in split(other.read_bytes())[0]["tensors"]}
    assert np.array_equal(load_nbvh(other).nodes["leaf"], nodes["leaf"])
    assert read_info(other).components["bvh"] == model.stored_bytes(res.settings.storage())["bvh"]
    # The root marked a leaf: too few internal nodes for the node count.
    at = names["bvh.shape"]["offset"]
    broken = bytearray(payload)
    broken[at] &= 0xFE
    with pytest.raises(NBVHFileError, match="shape bits are not a tree") as err:
        decode_nbvh(craft(header, bytes(broken)), "crafted.nbvh")
    assert "\n" not in str(err.value) and "crafted.nbvh" in str(err.value)
