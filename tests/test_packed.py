"""The storage variant (storage/packed.py): xz on disk, decoded at load to the exact traceable file; a crafted,
damaged or bomb-sized packed file is a one-line refusal that allocates nothing large."""
import lzma
import resource
import struct

import numpy as np
import pytest
import torch

from nbvh_core.app.cli import main
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.storage.fileformat import NBVHFileError, load_nbvh, read_info
from nbvh_core.storage.packed import PACKED_MAGIC, pack, unpack


@pytest.fixture(scope="module")
def model(sample_meshes, tmp_path_factory):
    path = tmp_path_factory.mktemp("packed") / "blob.nbvh"
    compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(force=True), path, evaluate_quality=False)
    return path


def test_a_packed_model_loads_to_the_same_model_in_fewer_bytes(model, tmp_path):
    data = model.read_bytes()
    packed = tmp_path / "blob.nbvhz"
    packed.write_bytes(pack(data))
    assert unpack(packed.read_bytes()) == data
    info = read_info(packed)
    assert info.total_bytes == len(data) and info.stored_bytes == packed.stat().st_size < len(data)
    a, b = load_nbvh(model), load_nbvh(packed)
    o = torch.rand(256, 3) * 0.2 - 0.1
    d = torch.nn.functional.normalize(torch.full((256, 3), 0.5) - o, dim=1)
    qa, qb = a.query(o, d), b.query(o, d)
    assert torch.equal(qa.hit, qb.hit) and torch.equal(qa.t, qb.t)


def test_the_pack_command_writes_beside_the_model_and_never_over_it(model, tmp_path, capsys):
    out = tmp_path / "m.nbvhz"
    assert main(["pack", str(model), "-o", str(out)]) == 0
    assert "on disk" in capsys.readouterr().out and out.exists()
    assert main(["pack", str(model), "-o", str(out)]) == 2  # exists: refused without --overwrite
    assert main(["pack", str(model), "-o", str(model), "--overwrite"]) == 2 and load_nbvh(model) is not None
    assert main(["info", str(out)]) == 0 and "packed" in capsys.readouterr().out


@pytest.mark.parametrize("case", ["bomb", "ratio", "truncated", "longer", "garbage"])
def test_crafted_packed_files_are_refused_in_one_line(model, tmp_path, case, capsys):
    data = model.read_bytes()
    good = pack(data)
    head = struct.Struct("<8sQ")
    if case == "bomb":  # declares 1 TB
        bad = head.pack(PACKED_MAGIC, 1 << 40) + good[head.size:]
    elif case == "ratio":  # 16 MB of zeros: xz makes it tiny; the ratio check refuses it before decoding
        bad = head.pack(PACKED_MAGIC, 16 << 20) + lzma.compress(bytes(16 << 20), format=lzma.FORMAT_XZ)
    elif case == "truncated":
        bad = good[: len(good) // 2]
    elif case == "longer":  # the stream holds more than declared
        bad = head.pack(PACKED_MAGIC, len(data) - 10) + good[head.size:]
    else:
        bad = PACKED_MAGIC + np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    path = tmp_path / f"{case}.nbvhz"
    path.write_bytes(bad)
    peak0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(NBVHFileError):
        load_nbvh(path)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak0 < 100_000  # KB
