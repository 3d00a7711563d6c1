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


def grid_faces(rows: int, cols: int) -> list[int]:
    """Flat triangle indices of a rows x cols vertex grid (row-major), two triangles per quad."""
    faces = []
    for i in range(rows - 1):
        for j in range(cols - 1):
            a = i * cols + j
            faces += [a, a + 1, a + cols, a + 1, a + cols + 1, a + cols]
    return faces


def newton_cloth(verts, faces, pinned=(), color: bool = True):
    """A finalized newton CPU model of one cloth mesh with the data's fabric (0.15 kg/m^2, membrane
    1e4, bending 1e-3, as ``ClothSimSettings``); ``pinned`` vertices get no mass."""
    from pocoloco.body.anny_body import quiet_warp

    quiet_warp()
    import warp as wp

    import newton

    b = newton.ModelBuilder()
    b.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                     vertices=[wp.vec3(*v) for v in verts], indices=faces, density=0.15, tri_ke=1e4, tri_ka=1e4,
                     tri_kd=1e-5, edge_ke=1e-3, edge_kd=0.0, particle_radius=0.004)  # fmt: skip
    for j in pinned:
        b.particle_mass[j] = 0.0
    if color:
        b.color()
    return b.finalize(device="cpu")
