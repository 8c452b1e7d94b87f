import os

import torch

# The card's Triton kernels run in Triton's CPU interpreter where there is no GPU (tests/test_triton_kernels.py);
# it is read when Triton is first imported, so it is set before anything imports it.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

# Budgets are read as the work they buy (planning/machine_rate.py): the tests pin this machine to the size
# predictor's own (a probe's rounding could otherwise move a pinned prediction on a much faster or slower machine);
# subprocesses inherit it. tests/test_machine_rate.py measures the probe itself.
os.environ.setdefault("NBVH_WORK_RATIO", "1")

import pytest

from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.geometry.bundled_samples import SAMPLE_NAMES, sample_path
from meshes import icosphere


@pytest.fixture(scope="session")
def sample_meshes():
    return {name: load_mesh(sample_path(name)) for name in SAMPLE_NAMES}


@pytest.fixture(scope="session")
def sample_bvhs(sample_meshes):
    return {name: build_bvh(m, 4096) for name, m in sample_meshes.items()}


@pytest.fixture(scope="session")
def sample_tracers(sample_meshes):
    return {name: ExactTracer(m) for name, m in sample_meshes.items()}


@pytest.fixture
def sphere_mesh():
    return icosphere(3)
