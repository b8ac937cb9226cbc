"""Every seeded set of simulated windows the project scores or checks with, in one registry.

Each set is filmed at the published window (:data:`~spk2img.sim.simulator.FILM_FRAMES`, 41
frames; a network with a shorter window reads their centred crop) from random generators keyed
``[seed, ...]``. A training batch draws from ``[run seed, rank, step, item]``: a key of another
length, so no set shares a draw with training, and no two sets share a seed
(``tests/test_simulator.py`` checks it). The builders live with their users, each taking
its seed from here.
"""

from __future__ import annotations

WINDOW_SETS: dict[str, int] = {
    # spk2img.evaluation.scoring.validation_set: procedural validation during training, and the
    # scenes of the export's hard cases
    "validation": 987_654_321,
    # validation_set(seed=TEST_SEED): the model cards' held-out procedural test, nothing else
    "test": 123_456_789,
    # spk2img.evaluation.natural_validation: held-out photos and clips (checkpoint selection,
    # model cards, bench --data)
    "natural": 2_468_013_579,
    # spk2img.bench.cases.benchmark_set and the streaming benchmark's stream
    "bench": 2_718_281_828,
    # spk2img.export.hard_cases: torch vs onnxruntime parity of every export
    "hard cases": 271_828,
    # spk2img.export.quantize.SimulatedWindows: int8 calibration
    "calibration": 161_803,
    # spk2img.evaluation.real_video: the sensor's initial charge of each real-video window
    "real video": 1_414_213_562,
}
"""Window set -> its seed."""


def seed_of(name: str) -> int:
    """The seed of window set ``name`` (a key of :data:`WINDOW_SETS`)."""
    return WINDOW_SETS[name]
