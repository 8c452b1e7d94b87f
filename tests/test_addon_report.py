"""The add-on's report module is plain Python: test it without Blender."""
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from addon.report import build_report, object_entry, write_report  # noqa: E402


def test_report_totals_ratios_and_html(tmp_path):
    png = tmp_path / "p.png"
    from PIL import Image

    Image.new("L", (4, 4), 128).save(png)
    job = {"file_bytes": 1000, "components": {"header": 100, "bvh": 300, "features": 400, "network": 200},
           "mesh_resident_bytes": {"total": 50_000}, "quality": {"mse": 0.002, "silhouette_iou": 0.97, "views": 16},
           "training": {"seconds": 12.5, "device": "cpu"}, "files": {"preview": str(png), "reference": str(png)}}
    turned = {"mse": 0.0023, "silhouette_iou": 0.96, "views": 16, "turn_seed": 1234}
    a = object_entry("A", {"total": 20_000, "positions": 12_000}, dict(job, quality_turned_views=turned))
    b = object_entry("B & <C>", {"total": 5_000, "positions": 3_000}, dict(job, file_bytes=500))
    rep = build_report([a, b])
    assert rep["totals"]["nbvh_bytes"] == 1500 and rep["totals"]["blender_mesh_bytes"] == 25_000
    assert a["ratio_blender_mesh_to_nbvh"] == 20 and a["ratio_resident_to_nbvh"] == 50
    js, htm = write_report(rep, tmp_path)
    assert json.loads(js.read_text())["objects"][1]["name"] == "B & <C>"
    page = htm.read_text()
    assert "B &amp; &lt;C&gt;" in page and page.count("data:image/png;base64") == 4 and "MSE 0.00200" in page
    assert page.count("views turned at random (seed 1234): MSE 0.00230, IoU 0.9600") == 1  # A's; B has none


def test_textures_count_as_blender_holds_them_and_in_bc7():
    from addon.report import texture_bytes

    rgba = texture_bytes(512, 512, 4, False)
    assert rgba["blender_bytes"] == 512 * 512 * 4
    # BC7: 1 byte per texel at the top level, the mip chain adds a third (blocks round up at the small levels)
    assert 512 * 512 < rgba["bc7_bytes"] < 512 * 512 * 4 / 3 * 1.01
    assert texture_bytes(1024, 1024, 4, True)["blender_bytes"] == 1024 * 1024 * 16  # float: 4 bytes a channel
    assert texture_bytes(3, 5, 3, False)["bc7_bytes"] == 2 * 16 + 16 + 16  # 1x2 blocks, then 1x1, 1x1


def test_the_whole_asset_saving_counts_textures_once(tmp_path):
    from addon.report import texture_bytes

    job = {"file_bytes": 10_000, "components": {"features": 10_000}, "mesh_resident_bytes": {"total": 400_000},
           "quality": {}, "training": {}, "files": {}}
    tex = {"albedo": texture_bytes(1024, 1024, 4, False)}  # 4 MB: most of the asset, as in real ones
    a = object_entry("A", {"total": 100_000}, job, tex, materials=2)
    assert a["ratio_blender_mesh_to_nbvh"] == 10  # geometry alone: 10x
    assert a["asset_bytes_before"] == 100_000 + 4 * 2 ** 20 and a["asset_bytes_after"] == 10_000 + 4 * 2 ** 20
    assert 1.0 < a["ratio_asset"] < 1.03  # the whole asset: barely smaller, and the report says so
    b = object_entry("B", {"total": 100_000}, job, tex)  # the same image on another object: counted once
    kept = [{"name": "C", "blender_mesh_bytes": {"total": 7_000}, "verdict": "kept", "textures": {}}]
    t = build_report([a, b], kept)["totals"]
    assert t["texture_bytes"] == 4 * 2 ** 20 and t["asset_bytes_before"] == 207_000 + 4 * 2 ** 20
    assert t["asset_bytes_after"] == 27_000 + 4 * 2 ** 20
    page = write_report(build_report([a, b], kept), tmp_path)[1].read_text()
    assert "in BC7 on a GPU" in page and "whole asset" in page and "material slots" in page
