"""`slam compare` that stops early keeps what it has: the table of the configs evaluated
before the stop, the partial outputs of the one stopped, and says where they are."""

from __future__ import annotations

import shutil

import pytest

import slam.run
from slam.cli import main
from slam.errors import InputError


def _compare(bag, gt, out, *configs, frames=20):
    return main(
        ["compare", str(bag), "--gt", str(gt), "--configs", *configs, "--out", str(out),
         "--max-frames", str(frames), "--quiet"]
    )  # fmt: skip


def test_ctrl_c_between_two_runs_still_writes_the_table(
    corridor_short, tmp_path, capsys, monkeypatch
):
    real, calls = slam.run.run_one, []

    def run_one(*args, **kwargs):  # Ctrl-C while the second config loads its kernels
        calls.append(args[1].name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(slam.run, "run_one", run_one)
    out = tmp_path / "cmp"
    code = _compare(
        corridor_short.bag, corridor_short.ground_truth, out, "floam", "improved_floam", "lego_loam"
    )
    assert code == 130
    assert calls == ["floam", "improved_floam"]
    captured = capsys.readouterr()
    rows = (out / "compare.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("floam,")
    assert "floam" in captured.out
    assert (out / "report.html").is_file()
    assert f"table, plots and report written to {out}/" in captured.err
    assert "improved_floam: stopped early: interrupted (Ctrl-C)\n" in captured.err
    assert "not run: lego_loam" in captured.err


def test_a_cut_input_too_short_to_evaluate_keeps_the_outputs(corridor_short, tmp_path, capsys):
    gt = tmp_path / "gt.tum"  # two poses of the ground truth: too few to align a trajectory
    gt.write_text("".join(corridor_short.ground_truth.read_text().splitlines(True)[:3]))
    out = tmp_path / "full"
    with pytest.raises(InputError, match="only 2 poses matched"):  # a whole run: bad input
        slam.run.run_one(
            corridor_short.bag, _floam(frames=12), out, gt=gt, quiet=True, label="floam"
        )
    cut = tmp_path / "cut.bag"  # 12 scans, then the file ends inside a record
    with corridor_short.bag.open("rb") as src, cut.open("wb") as dst:
        shutil.copyfileobj(src, dst)
        dst.truncate(corridor_short.bag.stat().st_size * 13 // 60)
    out = tmp_path / "cmp"
    assert _compare(cut, gt, out, "floam", "improved_floam") == 2
    err = capsys.readouterr().err
    assert "no run was evaluated: no table" in err
    assert "floam: not in the table: only 2 poses matched" in err
    assert f"floam: stopped early: bad input: {cut} is cut short" in err
    assert f"what it computed is in {out / 'floam'}/" in err
    assert "not run: improved_floam" in err
    rows = [r for r in (out / "floam" / "trajectory.tum").read_text().splitlines() if r[0] != "#"]
    assert len(rows) == 12


def _floam(frames):
    from slam.config import load_config

    config = load_config("floam")
    config.source.max_frames = frames
    return config


def test_ctrl_c_while_writing_the_outputs_still_writes_them(
    corridor_short, tmp_path, caplog, monkeypatch
):
    """The first Ctrl-C after the last frame waits for the outputs; the exit code says it came."""
    import os
    import signal

    import slam.outputs

    real = slam.outputs.write_outputs

    def write_outputs(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)

    monkeypatch.setattr(slam.outputs, "write_outputs", write_outputs)
    out = tmp_path / "run"
    code = main(["run", str(corridor_short.bag), "--config", "floam", "--out", str(out),
                 "--max-frames", "12", "--quiet"])  # fmt: skip
    assert code == 130
    rows = [r for r in (out / "trajectory.tum").read_text().splitlines() if r[0] != "#"]
    assert len(rows) == 12
    assert (out / "metrics.json").stat().st_size > 0 and (out / "map.pcd").stat().st_size > 0
    assert "writing the outputs first" in caplog.text
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
