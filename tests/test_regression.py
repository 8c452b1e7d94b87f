"""A seeded small training pinned to its recorded quality: a change that makes training 2x worse (or, unnoticed,
1.5x better: then re-record) fails here, where the other tests only catch a collapse."""
import pytest

from nbvh_core.app.pipeline import compress_mesh
from nbvh_core.planning.settings import preset

#: The blob, the preview method at T=2^10 and 255 nodes with the shape it was recorded with (4 levels of 8
#: features, 4 hidden layers, k = 8 points: pinned, so a preset's new shape does not move the record), 300 steps,
#: seed 0, 8 views at 64 px: image MSE measured 0.0052 and 0.0056 in two runs on the project's 2-core machine
#: (threads make the last digits vary).
RECORDED_MSE = 0.0054
#: The band: a 2x regression is outside it, the run-to-run spread (~8%) well inside.
BAND = 1.5


def test_a_seeded_small_training_keeps_its_recorded_quality(sample_meshes):
    s = preset("preview").with_overrides(steps=300, force=True, eval_views=8, eval_resolution=64, seed=0,
                                         log2_table=10, nodes=255, levels=4, features=8, hidden=4, k=8)
    s.time_limit_s = None
    res = compress_mesh(sample_meshes["blob"], s, None)
    mse = res.quality.mse
    assert RECORDED_MSE / BAND < mse < RECORDED_MSE * BAND, (
        f"MSE {mse:.5f} is {mse / RECORDED_MSE:.2f}x the recorded {RECORDED_MSE}: a regression (or an improvement "
        "to re-record)")
    assert res.quality.silhouette_iou > 0.93
