"""What a completion may never contain: negative predicted distances, repeated points."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from escape_cli import complete
from escape_cli.core.anchors import select_anchors
from escape_cli.core.encoding import distance_matrix
from escape_cli.core.normalize import network_input
from escape_cli.inference import load_model
from tests_support import partial_cloud


def test_network_output_is_never_negative(tiny_model, rng):
    net = load_model(str(tiny_model))
    shape = (3, net.input_points, net.k)
    for inputs in (rng.random(shape), rng.random(shape) * 50.0, np.zeros(shape), rng.normal(size=shape) * 5.0):
        assert net.predict(inputs.astype(np.float32)).min() >= 0.0
    cloud = partial_cloud(rng, 700)
    net_in = network_input(cloud, net.input_points, net.frame)
    anchors = select_anchors(net_in.observed)
    assert net.predict(distance_matrix(net_in.rows, anchors.points)[None]).min() >= 0.0


@pytest.mark.parametrize("size", [40, 250, 3000])
def test_completion_repeats_no_point(tiny_model, rng, size):
    out = complete(partial_cloud(rng, size), tiny_model, output_points=900)
    assert len(np.unique(out.points, axis=0)) == len(out.points)


def test_fewer_points_than_asked_are_said_so(tiny_model, rng, caplog):
    cloud = partial_cloud(rng, 300)
    with caplog.at_level(logging.WARNING, logger="escape"):
        out = complete(cloud, tiny_model, output_points=5000)
    assert len(out.points) == out.available < 5000
    assert out.summary()["available_points"] == out.available
    assert len(np.unique(out.points, axis=0)) == len(out.points)
    assert any("fewer than the 5000 asked for" in r.getMessage() for r in caplog.records)


def test_sparse_scans_drop_the_copies_their_repeated_rows_make(tiny_model, rng):
    """A 40-point scan fills the network's 256 rows by repetition; identical queries give identical points."""
    out = complete(partial_cloud(rng, 40), tiny_model, output_points=100_000)
    assert len(np.unique(out.points, axis=0)) == len(out.points) == out.available


def test_the_surplus_left_out_is_the_least_certain_part(tiny_model, rng):
    cloud = partial_cloud(rng, 3000)
    full = complete(cloud, tiny_model, output_points=100_000)
    kept = complete(cloud, tiny_model, output_points=full.available - 200)
    assert len(kept.points) == full.available - 200
    assert kept.is_observed.sum() == full.is_observed.sum()  # every observed point stays
    predicted = ~full.is_observed
    assert kept.residuals[~kept.is_observed].mean() < full.residuals[predicted].mean()
