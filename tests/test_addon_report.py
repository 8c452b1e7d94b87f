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
    a = object_entry("A", {"total": 20_000, "positions": 12_000}, job)
    b = object_entry("B & <C>", {"total": 5_000, "positions": 3_000}, dict(job, file_bytes=500))
    rep = build_report([a, b])
    assert rep["totals"]["nbvh_bytes"] == 1500 and rep["totals"]["blender_mesh_bytes"] == 25_000
    assert a["ratio_blender_mesh_to_nbvh"] == 20 and a["ratio_resident_to_nbvh"] == 50
    js, htm = write_report(rep, tmp_path)
    assert json.loads(js.read_text())["objects"][1]["name"] == "B & <C>"
    page = htm.read_text()
    assert "B &amp; &lt;C&gt;" in page and page.count("data:image/png;base64") == 4 and "MSE 0.00200" in page
