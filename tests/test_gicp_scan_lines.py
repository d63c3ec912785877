"""One-scan-line supports borrow the neighbouring scan line (slam.registration.covariances)."""

import numpy as np
import pytest

from slam.errors import ConfigError
from slam.registration.gicp import GicpConfig, estimate_covariances


def _two_rings(slope: float = 0.1, spacing: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Two 16-beam-like ground rings (7 and 8.5 m) on the plane z = slope * x, 5 mm noise."""
    rng = np.random.default_rng(0)
    rows = []
    for ring, r in enumerate([7.0, 8.5]):
        a = np.linspace(-0.5, 0.5, spacing)
        x, y = r * np.cos(a), r * np.sin(a)
        z = slope * x + rng.normal(0, 0.005, len(a))
        rows.append(np.c_[x, y, z, np.full(len(a), ring)])
    pts = np.concatenate(rows)
    return pts[:, :3], pts[:, 3].astype(int)


@pytest.mark.parametrize("spacing", [40, 200])  # 0.2 m and 4 cm along the ring
def test_one_line_support_gets_the_surface_normal(spacing):
    xyz, lab = _two_rings(spacing=spacing)
    q = xyz[:: max(spacing // 10, 1)]
    true = np.array([-0.1, 0.0, 1.0]) / np.linalg.norm([-0.1, 0.0, 1.0])
    iso = estimate_covariances(xyz, 10, 1e-6, "raw", query=q, labels=lab, span_distance=0.0)
    w, _ = np.linalg.eigh(iso)
    assert np.median(w[:, 0] / w[:, 2]) > 0.99  # fallback: isotropic, no normal
    cov = estimate_covariances(xyz, 10, 1e-6, "raw", query=q, labels=lab, span_distance=2.0)
    w, v = np.linalg.eigh(cov)
    angle = np.degrees(np.arccos(np.abs(v[:, :, 0] @ true)))
    assert angle.max() < 5.0  # the plane's normal, not the across-ring direction
    assert np.median(w[:, 0] / w[:, 2]) < 1e-3


def test_lines_farther_than_span_distance_stay_isotropic():
    xyz, lab = _two_rings()
    cov = estimate_covariances(xyz, 10, 1e-6, "raw", labels=lab, span_distance=1.0)  # gap 1.5 m
    w, _ = np.linalg.eigh(cov)
    assert np.allclose(w[:, 0] / w[:, 2], 1.0)


def test_negative_span_distance_is_a_config_error():
    with pytest.raises(ConfigError):
        GicpConfig(span_distance=-1.0)


def test_half_then_wide_search_equals_one_wide_search(monkeypatch):
    """The k_wide / 2 search, widened only where it cannot settle a row, gives the
    covariances of one k_wide search to the bit (rows settled by either search occur)."""
    import slam.registration.covariances as G

    rng = np.random.default_rng(3)
    rings = []
    for ring, r in enumerate([6.0, 6.8, 8.0, 11.0]):  # ring gaps 0.8, 1.2, 3 m
        n = int(rng.integers(60, 400))  # 1-6 cm apart along the ring: dense and sparse
        a = np.sort(rng.uniform(-0.4, 0.4, n))
        rings.append(np.c_[r * np.cos(a), r * np.sin(a), rng.normal(0, 0.01, n), np.full(n, ring)])
    pts = np.concatenate(rings)
    xyz, lab = pts[:, :3], pts[:, 3].astype(int)
    ks = []
    query = G.KnnTree.query

    def counting(self, x, k=1, **kw):
        ks.append(k)
        return query(self, x, k=k, **kw)

    monkeypatch.setattr(G.KnnTree, "query", counting)
    new = estimate_covariances(xyz, 10, 1e-6, "raw", labels=lab, span_distance=2.0)
    assert ks.count(20) == 1 and ks.count(40) == 1  # some rows needed the wide search

    def one_search(tree, x, k_wide, own, labels, m, span_distance, threads):
        d, j = tree.query(x, k=k_wide, distance_upper_bound=span_distance)
        return d.reshape(len(x), k_wide), j.reshape(len(x), k_wide)

    monkeypatch.setattr(G, "_wide_neighbours", one_search)
    ref = estimate_covariances(xyz, 10, 1e-6, "raw", labels=lab, span_distance=2.0)
    assert np.array_equal(new, ref)
