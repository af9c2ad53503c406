"""The calibration measurement of ``csr bench-uncertainty`` on hand-made maps: raw errors, the
2-sigma coverage, false elements and the certificate against the measured error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from csr_core.bench.uncertainty import calibration_row, calibration_table, element_errors
from csr_core.types import ElementType, MapFeature

pytestmark = pytest.mark.unit


def _line(y_m: float, length_m: float = 50.0, **props) -> MapFeature:
    xy = np.array([[0.0, y_m], [length_m, y_m]])
    return MapFeature(ElementType.LANE_DIVIDER, xy, properties=props)


def test_raw_errors_coverage_and_certificate():
    truth = [_line(0.0, 100.0), _line(3.5, 100.0)]
    predicted = [
        _line(0.3, sigma_abs_m=0.2, uncertainty_m=0.05, support_trips=2),  # 0.3 m off, within 2 sigma
        _line(3.5 + 0.5, 25.0, sigma_abs_m=0.2, uncertainty_m=0.05, support_trips=2),  # 0.5 m off: outside
        _line(20.0, sigma_abs_m=0.2, uncertainty_m=0.05),  # far from every divider: a false element
        _line(0.0, uncertainty_m=0.05),  # no sigma_abs_m: not measured
    ]
    errors, unmatched = element_errors(predicted, truth)
    assert unmatched == 1
    assert [e.error_m for e in errors] == pytest.approx([0.3, 0.5])
    assert [e.length_m for e in errors] == pytest.approx([50.0, 25.0])
    row = calibration_row("hand-made", errors, unmatched, trips=2)
    assert row.coverage_abs == 0.5 and row.coverage_rel == 0.0
    assert row.measured_m == pytest.approx(math.sqrt((50 * 0.09 + 25 * 0.25) / 75))
    assert row.expected_m == pytest.approx(0.2)
    assert row.ratio == pytest.approx(0.2 / row.measured_m)
    assert "| hand-made | 2 | 1 | 50 % | 0 % |" in calibration_table([row])
