"""Every result file can be traced: each CSV row, each Markdown report and each PNG in bench/results carries the
command that made it, the commit and the machine (bench/harness.py stamps them)."""
import csv
from pathlib import Path

from PIL import Image

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"
STAMP = ("commit", "machine", "command")  # the kernel plan and UTC joined the stamp later
PNG_STAMP_KEY = "nbvh-provenance"  # bench/harness.py


def _problem(path: Path) -> str | None:
    if path.suffix == ".csv":
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            return "no rows"
        if not all(k in rows[0] for k in STAMP) or not all(r.get(k) for r in rows for k in STAMP):
            return "a row without commit, machine or command"
    elif path.suffix == ".md":
        head = "\n".join(path.read_text().splitlines()[:4])
        if path.name != "PROVENANCE.md" and not ("Made by `" in head and " at commit " in head and " on " in head):
            return "no 'Made by `COMMAND` at commit C on MACHINE' in its first lines"
    elif path.suffix == ".png":
        text = Image.open(path).text.get(PNG_STAMP_KEY, "")
        if not (" at commit " in text and " on " in text):
            return f"no {PNG_STAMP_KEY} text chunk"
    else:
        return "not a result kind this test knows (csv, md, png)"
    return None


def test_every_result_file_is_stamped():
    tracked = [p for p in sorted(RESULTS.rglob("*")) if p.is_file() and not _ignored(p)]
    assert tracked
    problems = [f"{p.relative_to(RESULTS)}: {why}" for p in tracked if (why := _problem(p))]
    assert not problems, problems


def _ignored(path: Path) -> bool:
    """Files a benchmark leaves beside its results but git ignores (look_suzanne's scene and images)."""
    import subprocess

    out = subprocess.run(["git", "check-ignore", "-q", str(path)], cwd=RESULTS, capture_output=True)
    return out.returncode == 0


def test_the_stamp_check_catches_an_unstamped_file(tmp_path):
    (tmp_path / "a.csv").write_text("mesh,mse\nbunny,0.1\n")
    (tmp_path / "b.md").write_text("# Title\n\nnumbers\n")
    Image.new("RGB", (4, 4)).save(tmp_path / "c.png")
    assert all(_problem(tmp_path / n) for n in ("a.csv", "b.md", "c.png"))
