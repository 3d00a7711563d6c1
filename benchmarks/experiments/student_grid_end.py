"""A 2-call student whose second call is at another step than its grid's last (issue 42).

``python benchmarks/experiments/student_grid_end.py S ARGS...`` runs ``pocoloco ARGS...`` with
:func:`pocoloco.diffusion.few_step.sampling_grid` answering ``[999, S]`` for 2 calls (a student
trained on 999, 749, 499, 249 samples 2 calls on 999, 249): does ending lower than the student's
least noisy trained step help? Any other number of calls is left as it is. E.g.

    python benchmarks/experiments/student_grid_end.py 149 bench quality --data DATA --split test \\
        --frames 28 --seeds 0 1 --points 2048 --ckpt-pocoloco default:fast --steps 2 --out OUT
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> int:
    import pocoloco.methods.pocoloco.method as method
    import pocoloco.methods.pocoloco.sampling as sampling

    end = int(argv[0])
    trained = sampling.sampling_grid

    def grid(num_timesteps: int, calls: int, trained_calls: int) -> list[int]:
        g = trained(num_timesteps, calls, trained_calls)
        return [g[0], end] if calls == 2 else g

    sampling.sampling_grid = method.sampling_grid = grid
    from pocoloco.cli import main as cli

    return cli(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
