"""Bytes per km of the upload forms (``csr_core.bench.upload_size``, ``csr bench-upload-size``)."""

from __future__ import annotations

import gzip

import pytest

from csr_core.bench.upload_size import GZIP_LEVEL, markdown, measure
from csr_core.scenario import list_trip_files
from csr_core.sim import simulate_scenario

pytestmark = pytest.mark.unit


def test_sizes_per_km_and_the_lossless_binary_reconstructs_as_the_json(tmp_path):
    simulate_scenario("urban", n_trips=1, profile="standard", seed=4, out_dir=tmp_path, trip_length_m=200.0)
    sizes, reconstructions = measure(tmp_path, n_reconstruct=1)
    by_name = {row.variant: row for row in sizes}
    (trip_file,) = list_trip_files(tmp_path)
    json_body = gzip.decompress(trip_file.path.read_bytes())
    assert by_name["JSON"].bytes_total == len(json_body)
    assert by_name["JSON, gzip"].bytes_total == len(gzip.compress(json_body, compresslevel=GZIP_LEVEL))
    assert 0.15 < by_name["JSON"].km < 0.25  # the true poses' length, 200 m asked
    assert (
        by_name["binary, keyframes every 5.5 m, 1 cm points, gzip"].bytes_total
        < by_name["binary, gzip"].bytes_total
        < by_name["JSON, gzip"].bytes_total
    )
    rows = {row.variant: row for row in reconstructions}
    reference, lossless = rows["JSON, gzip"], rows["binary, gzip"]
    assert lossless.max_offset_from_json_m == 0.0
    assert (lossless.n_instances, lossless.instances_mcd_m) == (
        reference.n_instances,
        reference.instances_mcd_m,
    )
    assert reference.n_instances > 0 and 0.0 < reference.instances_mcd_m < 1.0
    table = markdown(sizes, reconstructions)
    assert "| binary, gzip |" in table and "instances' mCD [m]" in table
