"""Average checkpoints of one lineage into a release checkpoint (a "model soup").

``python scripts/average_checkpoints.py A.pt B.pt [...] --weights 0.5,0.5 --out SOUP.pt`` writes
the weighted mean of the networks' weights (same member and config) with the last source's
metadata and an ``averaged_from`` record (:func:`spk2img.model.checkpoint.average_checkpoints`).
Equal weights when ``--weights`` is left out; a weight may be a fraction (``2/3,1/3``).
``--chosen-on "real video frames"`` records what the mean was chosen on (its model card says
so) in place of the last source's record.
Interpolating a fine-tuned checkpoint with the one it started from can keep what each does best:
the shipped ``default``'s weights are such a mean (docs/model_card.md). ``scripts/ship_model.sh``
ships it when it is a run folder's ``best.pt``.
"""

from __future__ import annotations

import argparse
import sys
from fractions import Fraction

from spk2img.errors import InputError
from spk2img.model.checkpoint import average_checkpoints
from spk2img.training.train import SELECTIONS


def fail(message: str) -> None:
    """One line on stderr and exit code 2 (bad input), as the spk2img CLI does."""
    print(f"average_checkpoints: {message}", file=sys.stderr)
    sys.exit(2)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", help="training or release checkpoints (.pt)")
    p.add_argument(
        "--weights", help="comma-separated numbers or fractions, one per checkpoint, summing to 1"
    )
    p.add_argument("--out", required=True, help="the averaged release checkpoint (.pt)")
    p.add_argument(
        "--chosen-on",
        choices=SELECTIONS,
        help="the validation the mean was chosen on (default: the last source's record)",
    )
    args = p.parse_args()
    n = len(args.checkpoints)
    try:
        weights = (
            [float(Fraction(w)) for w in args.weights.split(",")] if args.weights else [1 / n] * n
        )
    except (ValueError, ZeroDivisionError):
        fail(f"--weights {args.weights!r} is not a list of numbers")
    try:
        average_checkpoints(args.checkpoints, weights, args.out, args.chosen_on)
    except InputError as exc:
        fail(str(exc))
    print(
        f"wrote {args.out}: "
        + ", ".join(f"{w:g} x {c}" for w, c in zip(weights, args.checkpoints, strict=True))
    )


if __name__ == "__main__":
    main()
