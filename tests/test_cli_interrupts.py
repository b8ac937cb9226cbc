"""SIGTERM (``timeout``, ``kill``, a scheduler) stops any command as Ctrl-C does: what the
command was writing is cleaned up or kept for ``--resume``, and it exits 143
(spk2img.cli.interrupts). ``reconstruct``'s case is in test_reconstruct_resume.py, ``train``'s
in test_training.py."""

from __future__ import annotations

import os
import signal
import time

import pytest

from spk2img.cli import interrupts, main
from spk2img.export import pipeline


def _terminate_now(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(30)  # the handler raises before this ends
    pytest.fail("SIGTERM did not stop the command")


def test_a_terminated_export_leaves_no_temporary_folder(tmp_path, monkeypatch, capsys):
    """Killed inside its temporary folder: no ``.spk2img-export-*`` folder and no model are left
    beside ``--out`` (SIGTERM used to end the process inside the folder's ``with`` block)."""
    monkeypatch.setattr(pipeline, "find_template", _terminate_now)
    previous = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "models" / "m.onnx"
    argv = ["export", "--random-weights", "--member", "tiny", "--out", str(out)]
    assert main(argv) == 143
    assert capsys.readouterr().err.strip().endswith("spk2img: terminated")
    assert list(out.parent.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is previous


def test_exit_codes_follow_the_signal():
    assert interrupts.exit_code(KeyboardInterrupt()) == 130
    assert interrupts.exit_code(interrupts.Terminated()) == 143
