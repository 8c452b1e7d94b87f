"""What a run is asked to do (settings, presets) and how big a model it needs (sizing, verdicts)."""
