"""Input encodings: one interface (`base.Encoding`: `forward(points (N, 3) in [0, 1]^3) -> (N, out_dim)`,
`stored_bytes()`, capability flags and the training life-cycle hooks).

`make_encoding(cfg)` picks the class from `cfg.kind`, so an ablation is a config change.
"""
from .base import Encoding, EncodingConfig
from .hashgrid import HashGrid
from .hashvqad import HashVQAD

ENCODINGS = {"hashgrid": HashGrid, "hashvqad": HashVQAD}


def make_encoding(cfg: EncodingConfig, inference: bool = False) -> Encoding:
    """The encoding `cfg.kind` names; `inference=True` allocates no trainable state (the file reader fills it)."""
    if cfg.kind not in ENCODINGS:
        raise ValueError(f"unknown encoding {cfg.kind!r}; choose from {', '.join(ENCODINGS)}")
    return ENCODINGS[cfg.kind](cfg, inference)


__all__ = ["Encoding", "EncodingConfig", "HashGrid", "HashVQAD", "ENCODINGS", "make_encoding"]
