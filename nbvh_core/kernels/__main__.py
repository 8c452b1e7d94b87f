"""`python -m nbvh_core.kernels build`: compile the fused kernels now (install time); otherwise print the path."""
import sys

from . import build, describe

if sys.argv[1:] == ["build"]:
    try:
        print(build(verbose=True))
    except RuntimeError as exc:  # the reference path still works: say so, do not fail the install
        print(f"warning: {exc}\nthe reference (pure torch) path will be used", file=sys.stderr)
else:
    print(describe())
