import os
import sys
from pathlib import Path

import pytest

# keep BLAS and torch to the machine's 2 cores and make runs reproducible
os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="module")
def torch_single_thread():
    """Run a test module with one torch thread (restored afterwards)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A dataset generated once per test session with the ``tiny`` preset."""
    from pocoloco.synth.config import synth_preset
    from pocoloco.synth.pipeline import synthesize

    out = tmp_path_factory.mktemp("tiny") / "data"
    synthesize(synth_preset("tiny"), out)
    return out


@pytest.fixture(scope="session")
def tiny_run(tiny_dataset, tmp_path_factory) -> Path:
    """A tiny model trained for 2 steps on ``tiny_dataset`` (its run folder), shared by the test modules."""
    from pocoloco.methods import train
    from pocoloco.methods.pocoloco import train_preset

    out = tmp_path_factory.mktemp("tiny_run") / "run"
    cfg = train_preset("tiny", steps=2, batch_size=2, num_points=128, ckpt_every=0, sample_every=0, log_every=1)
    train(cfg, tiny_dataset, out, progress=False)
    return out


def run_cli(*args: str, env: dict | None = None):
    """Run ``python -m pocoloco.cli ARGS`` in a subprocess; returns CompletedProcess."""
    import subprocess

    return subprocess.run(
        [sys.executable, "-m", "pocoloco.cli", *args],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=600,
    )
