"""The add-on's dependency installer (addon/installer.py, no bpy): the commands per OS (the CPU build of PyTorch,
Windows' Scripts\\python.exe) and the watched background steps (progress, the current pip line, failure, cancel)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.installer import (TORCH_CPU_INDEX, TORCH_CUDA_INDEX, Installer, Step, install_steps,  # noqa: E402
                             nvidia_card, venv_python)

REQ = ROOT / "nbvh_core" / "requirements.txt"


def test_commands_pick_the_cpu_build_and_the_platform_paths(tmp_path):
    assert venv_python(tmp_path, "nt") == tmp_path / "Scripts" / "python.exe"
    assert venv_python(tmp_path, "posix") == tmp_path / "bin" / "python"
    linux = install_steps(tmp_path / "v", "/usr/bin/python3", REQ, system="Linux", os_name="posix", card=None)
    assert [s.label for s in linux][0] == "creating the virtual environment"
    torch_step = next(s for s in linux if "PyTorch" in s.label)
    assert "torch==2.13.0" in torch_step.cmd and torch_step.cmd[-2:] == ["--index-url", TORCH_CPU_INDEX]
    assert torch_step.cmd[0] == str(tmp_path / "v" / "bin" / "python")
    windows = install_steps(tmp_path / "w", "python.exe", REQ, system="Windows", os_name="nt", card=None)
    assert next(s for s in windows if "PyTorch" in s.label).cmd[0] == str(tmp_path / "w" / "Scripts" / "python.exe")
    mac = install_steps(tmp_path / "m", "python3", REQ, system="Darwin", os_name="posix")
    assert "--index-url" not in next(s for s in mac if "PyTorch" in s.label).cmd  # PyPI's macOS wheels are CPU
    (tmp_path / "e" / "bin").mkdir(parents=True)
    (tmp_path / "e" / "bin" / "python").write_text("")
    assert "creating" not in install_steps(tmp_path / "e", "python3", REQ, os_name="posix", card=None)[0].label


def test_a_card_gets_the_cuda_build_and_says_what_runs_on_it(tmp_path, monkeypatch):
    """With an NVIDIA card: on Linux PyPI's wheel (the CUDA build, Triton with it), on Windows PyTorch's CUDA index
    (no Triton there: the label says torch's CUDA kernels run); macOS has no CUDA build. The card comes from the
    driver's own list (`nvidia-smi -L`); no driver or a failing one is no card."""
    import subprocess
    from types import SimpleNamespace

    card = "GPU 0: NVIDIA H100 80GB HBM3"
    linux = next(s for s in install_steps(tmp_path / "v", "python3", REQ, system="Linux", os_name="posix",
                                          card=card) if "PyTorch" in s.label)
    assert "--index-url" not in linux.cmd and "CUDA build with Triton" in linux.label and card in linux.label
    windows = next(s for s in install_steps(tmp_path / "w", "python.exe", REQ, system="Windows", os_name="nt",
                                            card=card) if "PyTorch" in s.label)
    assert windows.cmd[-2:] == ["--index-url", TORCH_CUDA_INDEX] and "no Triton on Windows" in windows.label
    mac = next(s for s in install_steps(tmp_path / "m", "python3", REQ, system="Darwin", os_name="posix", card=card)
               if "PyTorch" in s.label)
    assert "CUDA" not in mac.label
    import addon.installer as installer

    monkeypatch.setattr(installer.shutil, "which", lambda name: "/usr/bin/nvidia-smi")
    listed = lambda *a, **k: SimpleNamespace(returncode=0, stdout=f"{card} (UUID: GPU-1234)\n")  # noqa: E731
    assert nvidia_card(listed) == card
    assert nvidia_card(lambda *a, **k: SimpleNamespace(returncode=9, stdout="")) is None

    def broken(*a, **k):
        raise subprocess.TimeoutExpired("nvidia-smi", 10)
    assert nvidia_card(broken) is None
    monkeypatch.setattr(installer.shutil, "which", lambda name: None)
    assert nvidia_card(listed) is None
    assert "CPU build: no NVIDIA card" in next(
        s for s in install_steps(tmp_path / "n", "python3", REQ, system="Linux", os_name="posix") if "PyTorch" in s.label
    ).label


def _run(inst: Installer, timeout: float = 30.0) -> list[tuple[str, float, str]]:
    seen = []
    inst.start()
    t0 = time.monotonic()
    while inst.poll() == "running" and time.monotonic() - t0 < timeout:
        seen.append((inst.phase, inst.fraction, inst.line))
        time.sleep(0.05)
    return seen


def test_steps_run_in_order_with_progress_and_the_current_line():
    py = sys.executable
    inst = Installer([Step("one", [py, "-c", "print('Collecting torch'); import time; time.sleep(0.5)"]),
                      Step("two", [py, "-c", "print('Installing collected packages: numpy')"])])
    seen = _run(inst)
    assert inst.state == "done" and inst.fraction == 1.0
    assert ("one", 0.0, "Collecting torch") in seen
    assert inst.log == ["Collecting torch", "Installing collected packages: numpy"]


def test_a_failed_step_stops_with_its_output():
    py = sys.executable
    inst = Installer([Step("pip", [py, "-c", "import sys; print('ERROR: No matching distribution'); sys.exit(1)"]),
                      Step("never", [py, "-c", "print('not run')"])])
    _run(inst)
    assert inst.state == "failed" and "pip failed (exit 1)" in inst.error and "No matching distribution" in inst.error
    assert "not run" not in inst.log


def test_cancel_stops_the_running_step_at_once():
    inst = Installer([Step("slow", [sys.executable, "-c", "import time; time.sleep(60)"])])
    inst.start()
    time.sleep(0.3)
    t0 = time.monotonic()
    inst.cancel()
    assert inst.state == "cancelled" and time.monotonic() - t0 < 5 and inst._proc.poll() is not None


def test_the_add_on_installs_exactly_the_pins_the_project_declares():
    """requirements.txt (what the add-on's installer pins) lists pyproject.toml's dependencies, no more, no less."""
    import tomllib

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    listed = [ln.strip() for ln in REQ.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert sorted(listed) == sorted(declared)


def test_one_version_everywhere():
    """pyproject.toml's version is the package's, the add-on's bl_info and its extension manifest's."""
    import re
    import tomllib

    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    manifest = tomllib.loads((ROOT / "addon" / "blender_manifest.toml").read_text())["version"]
    core = re.search(r'__version__ = "([^"]+)"', (ROOT / "nbvh_core" / "__init__.py").read_text()).group(1)
    bl_info = re.search(r'"version": \((\d+), (\d+), (\d+)\)', (ROOT / "addon" / "__init__.py").read_text()).groups()
    assert version == manifest == core == ".".join(bl_info)
