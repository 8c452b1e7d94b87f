"""Installing the job Python's dependencies in the background: a virtual environment with PyTorch (the CUDA build
where an NVIDIA card is found, else the CPU build) and nbvh_core's pinned requirements, step by step in watched
processes (progress, the pip line being worked on, cancel), so Blender's UI never waits on pip. No bpy and no torch
here.

    inst = Installer(install_steps(venv_dir, base_python, requirements))
    inst.start(); ... inst.poll() (from a timer) ...; inst.cancel()
"""
from __future__ import annotations

import os
import platform
import queue
import re
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

#: PyTorch's own index of CPU-only wheels (the PyPI wheel on Linux is the CUDA build, several GB).
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
#: PyTorch's index of CUDA wheels, for Windows (on Linux the PyPI wheel is the CUDA build and brings Triton). CUDA 13.0:
#: the build a lent card's image runs (torch 2.11+cu130); its driver must be 580 or newer.
TORCH_CUDA_INDEX = "https://download.pytorch.org/whl/cu130"


def nvidia_card(run=subprocess.run) -> str | None:
    """The first NVIDIA card as the driver lists it (`nvidia-smi -L`: 'GPU 0: NVIDIA ... (UUID: ...)'), or None
    when there is no driver or no card. run: subprocess.run (a test's stand-in)."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None
    try:
        out = run([exe, "-L"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return next((ln.split(" (UUID")[0].strip() for ln in out.stdout.splitlines() if ln.startswith("GPU ")), None)


def venv_python(venv_dir: str | Path, os_name: str = os.name) -> Path:
    """The interpreter of a virtual environment: Scripts\\python.exe on Windows, bin/python elsewhere."""
    venv_dir = Path(venv_dir)
    return venv_dir / "Scripts" / "python.exe" if os_name == "nt" else venv_dir / "bin" / "python"


def torch_requirement(requirements: Path) -> str:
    """The pinned torch line of requirements.txt (e.g. 'torch==2.13.0')."""
    for line in requirements.read_text().splitlines():
        if re.match(r"\s*torch\s*[=<>~]", line):
            return line.strip()
    return "torch"


def stop_process(proc: subprocess.Popen | None, timeout_s: float = 10.0) -> None:
    """Terminate a running child process, killing it when it does not end within timeout_s."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@dataclass
class Step:
    label: str
    cmd: list[str]


def install_steps(venv_dir: str | Path, base_python: str, requirements: Path, system: str | None = None,
                  os_name: str = os.name, card: str | None | bool = True) -> list[Step]:
    """The commands, in order: create the environment (unless it exists), PyTorch, the other requirements, a check.
    PyTorch is the CUDA build where an NVIDIA card is found (Linux: PyPI's wheel, which brings Triton, so the card
    runs the fused Triton kernels; Windows: PyTorch's CUDA index, without Triton: the card runs torch's own CUDA
    kernels and the run's kernel plan says so), else the CPU build (PyTorch's CPU index on Linux and Windows; macOS
    wheels on PyPI are CPU builds). card: the card found (True: look for one with `nvidia_card`; None: none)."""
    system = system or platform.system()
    card = nvidia_card() if card is True and system in ("Linux", "Windows") else (card or None)
    py = str(venv_python(venv_dir, os_name))
    steps = []
    if not Path(py).exists():
        steps.append(Step("creating the virtual environment", [base_python, "-m", "venv", str(venv_dir)]))
    torch_cmd = [py, "-m", "pip", "install", "--progress-bar", "off", torch_requirement(requirements)]
    if card and system == "Linux":
        label = f"installing PyTorch (CUDA build with Triton, for {card})"
    elif card and system == "Windows":
        torch_cmd += ["--index-url", TORCH_CUDA_INDEX]
        label = f"installing PyTorch (CUDA build, for {card}; no Triton on Windows: torch's CUDA kernels run)"
    elif system in ("Linux", "Windows"):
        torch_cmd += ["--index-url", TORCH_CPU_INDEX]
        label = "installing PyTorch (CPU build: no NVIDIA card found)"
    else:
        label = "installing PyTorch (CPU build)"
    steps.append(Step(label, torch_cmd))
    steps.append(Step("installing nbvh_core's dependencies",
                      [py, "-m", "pip", "install", "--progress-bar", "off", "-r", str(requirements)]))
    steps.append(Step("checking", [py, "-c", "import torch, numpy; print('torch', torch.__version__, 'CUDA' if "
                                             "torch.cuda.is_available() else 'CPU')"]))
    return steps


@dataclass
class Installer:
    """Runs `steps` one after another. state: queued -> running -> done | failed | cancelled; `line`: the last
    output line (what pip is doing), `fraction`: steps done (+ a part of the current one), `error` on failure."""

    steps: list[Step]
    env: dict | None = None
    #: The interpreter of the environment the steps set up (the preferences' Python once they are done).
    python: str = ""
    state: str = "queued"
    index: int = 0
    line: str = ""
    error: str = ""
    log: list = field(default_factory=list)
    _proc: subprocess.Popen | None = None
    _lines: queue.Queue = field(default_factory=queue.Queue)

    @property
    def phase(self) -> str:
        return self.steps[self.index].label if self.index < len(self.steps) else "done"

    @property
    def fraction(self) -> float:
        return 1.0 if self.state == "done" else min(self.index, len(self.steps)) / max(len(self.steps), 1)

    def start(self) -> None:
        self.state = "running"
        self._launch()

    def _launch(self) -> None:
        step = self.steps[self.index]
        self._proc = subprocess.Popen(step.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      env=self.env)
        threading.Thread(target=self._read, args=(self._proc.stdout,), daemon=True).start()

    def _read(self, stream) -> None:
        for text in stream:
            self._lines.put(text.rstrip())

    def poll(self) -> str:
        """Advance (from a timer): read output, start the next step when one ends. Returns the state."""
        while True:
            try:
                text = self._lines.get_nowait()
            except queue.Empty:
                break
            if text:
                self.line = text[-160:]
                self.log.append(text)
                del self.log[:-400]
        if self.state != "running" or self._proc is None or self._proc.poll() is None:
            return self.state
        code = self._proc.returncode
        if code != 0:
            self.state = "failed"
            tail = "\n".join(self.log[-12:])
            self.error = f"{self.phase} failed (exit {code})" + (f":\n{tail}" if tail else "")
            return self.state
        self.index += 1
        if self.index >= len(self.steps):
            self.state = "done"
        else:
            self._launch()
        return self.state

    def cancel(self) -> None:
        """Stop the running step now (a half-made environment stays; the next install continues it)."""
        stop_process(self._proc)
        if self.state in ("queued", "running"):
            self.state = "cancelled"


def default_base_python() -> str:
    """The Python a new environment is made from: python3 on PATH, else the one running (Blender's own)."""
    import shutil

    return shutil.which("python3") or shutil.which("python") or sys.executable
