"""`slam simulate` refuses what it cannot do before it writes anything."""

from __future__ import annotations

from slam.cli import main


def test_an_unknown_scene_lists_the_3d_and_the_2d_scenes(tmp_path, capsys):
    assert main(["simulate", "nosuch", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "'urban'" in err and "'rooms2d'" in err
    assert not (tmp_path / "out").exists()


def test_a_2d_scene_refuses_a_bag_format_or_a_3d_sensor(tmp_path, capsys):
    assert main(["simulate", "rooms2d", str(tmp_path / "a"), "--format", "mcap"]) == 2
    assert main(["simulate", "rooms2d", str(tmp_path / "b"), "--sensor", "hdl64"]) == 2
    assert "CARMEN log" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
