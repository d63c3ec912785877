"""A nested section given in part overrides only its given fields of the default its parent
section gives it (a default_factory's values), at any depth, also through ``X | None``."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam import plugins
from slam.config import build_dataclass


@dataclass
class Grid:
    resolution: float = 0.05
    hit: float = 0.85
    clamp: float = 3.5


@dataclass
class Inner:
    grid: Grid = field(default_factory=lambda: Grid(hit=2.0))
    scale: float = 1.0


@dataclass
class Outer:
    submap: Grid = field(default_factory=lambda: Grid(hit=1.0, clamp=300.0))
    region: Grid = field(default_factory=Grid)
    inner: Inner = field(default_factory=lambda: Inner(grid=Grid(hit=3.0, clamp=9.0), scale=2.0))
    maybe: Grid | None = field(default_factory=lambda: Grid(clamp=7.0))


def test_a_partial_section_keeps_the_parents_default_for_the_fields_not_given():
    cfg = build_dataclass(Outer, {"submap": {"resolution": 0.1}, "region": {"hit": 0.5}})
    assert cfg.submap == Grid(resolution=0.1, hit=1.0, clamp=300.0)  # not Grid's 0.85 / 3.5
    assert cfg.region == Grid(hit=0.5)
    assert build_dataclass(Outer, {}).submap == Grid(hit=1.0, clamp=300.0)


def test_nested_partial_sections_keep_the_defaults_at_every_depth():
    cfg = build_dataclass(Outer, {"inner": {"grid": {"resolution": 0.2}}, "maybe": {"hit": 4.0}})
    assert cfg.inner == Inner(grid=Grid(resolution=0.2, hit=3.0, clamp=9.0), scale=2.0)
    assert cfg.maybe == Grid(hit=4.0, clamp=7.0)
    assert build_dataclass(Outer, {"maybe": None}).maybe is None


def test_the_dpcr2d_submap_grid_keeps_its_counting_log_odds_when_one_field_is_given():
    cls = plugins.load("slam.frontends", "dpcr2d")
    cfg = plugins.plugin_config(cls, {"submap_grid": {"resolution": 0.1}}, "frontend")
    grid = cfg.submap_grid
    assert (grid.resolution, grid.hit, grid.miss, grid.clamp) == (0.1, 1.0, -1.0, 300.0)
