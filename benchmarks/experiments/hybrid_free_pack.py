"""Pack the free region of a dataset for the hybrid method's generator (issue 26).

Learns the free-region maps (``pocoloco.methods.hybrid.regions``) from the train split, renders
them, and writes a training pack whose points are drawn only where the cloth hangs free (each
point's nearest posed body vertex is free), for the outfits with a free region. Training PocoLoco on
that pack (``pocoloco train --data PACK --init-from default``) gives the free-region generator;
``pocoloco hybrid --fine-tune MINUTES`` runs both steps and the assembly in one command.

    python benchmarks/experiments/hybrid_free_pack.py --data ~/.cache/pocoloco/data/medium \
        --out ~/.cache/pocoloco/hybrid
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pocoloco.methods.hybrid import learn_free_maps, render_free_maps
from pocoloco.methods.hybrid.training import write_free_pack


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--out", required=True, help="folder for maps.npz, maps.png and free.pack")
    p.add_argument("--margin", type=float, default=0.03)
    p.add_argument("--threshold", type=float, default=0.5)
    p.add_argument("--every", type=int, default=3, help="pack every K-th train frame")
    p.add_argument("--points", type=int, default=512)
    p.add_argument("--min-share", type=float, default=0.05, help="outfits with a smaller free share are left out")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    maps = learn_free_maps(args.data, margin=args.margin, threshold=args.threshold)
    maps.save(out / "maps.npz")
    render_free_maps(maps, args.data, out / "maps.png")
    meta = write_free_pack(args.data, maps, out / "free.pack", every=args.every, points=args.points,
                           min_share=args.min_share)  # fmt: skip
    chosen = meta["packed"]
    summary = {"outfits": list(maps.outfits), "point_share": [round(float(x), 4) for x in maps.point_share],
               "packed": chosen, "frames": meta["splits"], "skipped": meta["skipped"], "bytes": meta["bytes"]}  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
