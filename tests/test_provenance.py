"""Every result file can be traced: a CSV in bench/results is stamped (commit, machine, kernel plan, command, UTC on
every row) or listed in bench/results/PROVENANCE.md as made before stamping, with the script that made it."""
import csv
import re
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"
STAMP = ("commit", "machine", "command")  # the kernel plan and UTC joined the stamp later


def test_every_result_csv_is_stamped_or_listed_as_unstamped():
    listed = set(re.findall(r"\| `([^`]+\.csv)` \| `bench/([^`]+\.py)` \|", (RESULTS / "PROVENANCE.md").read_text()))
    unstamped = {name for name, script in listed}
    assert all((RESULTS.parent / script).exists() for _, script in listed)
    problems = []
    for path in sorted(RESULTS.glob("*.csv")):
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        header = rows[0].keys() if rows else []
        stamped = all(k in header for k in STAMP) and all(r.get("commit") for r in rows)
        if not stamped and path.name not in unstamped:
            problems.append(f"{path.name}: no stamp and not listed in PROVENANCE.md")
        if stamped and path.name in unstamped:
            problems.append(f"{path.name}: stamped now; drop it from the unstamped list")
    assert not problems, problems
