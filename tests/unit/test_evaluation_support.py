"""What the benches share: a table has its header and rule, each result lands as Markdown
and JSON (numpy values included), a row that does not fit its header is refused; the
disparity measures count only the pixels known in both maps; a curve's errors are exact
distances to the true segments, its coverage the share of the true length near the
points' polyline."""

import json

import numpy as np
import pytest
from vgm_evaluation.bench_report import markdown_table, write_results
from vgm_evaluation.metrics import curve_agreement, disparity_agreement


def test_table_rows_under_their_columns():
    lines = markdown_table(('pair', 'ms'), [['Aloe', '96'], ['default', 12]])
    assert lines == ['| pair | ms |', '|---|---|', '| Aloe | 96 |', '| default | 12 |']


def test_a_row_of_the_wrong_width_is_refused():
    with pytest.raises(ValueError, match='a row of 1 cells under 2 columns'):
        markdown_table(('pair', 'ms'), [['Aloe']])


def test_results_written_as_markdown_and_json(tmp_path, capsys):
    data = {'rms_mm': np.float32(0.25), 'ok': np.bool_(True), 'errors': np.array([1, 2])}
    markdown = write_results(tmp_path / 'sfs', 'speed', ['# title', 'line'], data)
    assert markdown.read_text() == '# title\nline\n'
    assert json.loads((tmp_path / 'sfs' / 'speed.json').read_text()) == {
        'rms_mm': 0.25,
        'ok': True,
        'errors': [1, 2],
    }
    assert '# title' in capsys.readouterr().out


def test_disparity_agreement_counts_only_pixels_known_in_both():
    truth = np.array([[1.0, 2.0, np.nan], [4.0, 5.0, 6.0]])
    estimate = np.array([[1.0, 2.0, 9.0], [np.nan, 5.0, 10.0]])  # 4 shared, one 4 px off
    agreement = disparity_agreement(estimate, truth)
    assert agreement.rms_px == pytest.approx(np.sqrt(16 / 4))
    assert agreement.beyond_2px == pytest.approx(1 / 4)
    assert agreement.correlation == pytest.approx(np.corrcoef([1, 2, 5, 10], [1, 2, 5, 6])[0, 1])
    assert disparity_agreement(None, truth).correlation == 0.0


def test_curve_agreement_against_a_straight_true_curve():
    truth = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])  # [m] one segment, 100 mm
    # 1 mm and 2 mm off the segment, then 50 mm beyond its end
    points = np.array([[0.02, 0.001, 0.0], [0.05, 0.0, 0.002], [0.15, 0.0, 0.0]])
    agreement = curve_agreement(points, truth)
    np.testing.assert_allclose(agreement.distance_m, [0.001, 0.002, 0.05], atol=1e-12)
    assert agreement.rms_m == pytest.approx(np.sqrt((1e-6 + 4e-6 + 2.5e-3) / 3))
    assert agreement.max_m == pytest.approx(0.05)
    # the true curve's first 20 mm lie before the polyline's first point: covered up to
    # sqrt(3^2 - 1^2) mm before it, the rest of the 100 mm within 2 mm of it
    assert agreement.coverage == pytest.approx((0.08 + np.sqrt(8e-6)) / 0.1, abs=2e-3)
    assert agreement.farthest_uncovered_m == pytest.approx(np.hypot(0.02, 0.001))


def test_curve_agreement_closes_what_is_closed_and_keeps_pieces_apart():
    square = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.1, 0.0]])
    # the same square 1 mm above: open, its closing side is missing
    above = square + [0.0, 0.0, 0.001]
    open_ = curve_agreement(above, square, closed=False, truth_closed=True)
    closed = curve_agreement(above, square, closed=True, truth_closed=True)
    np.testing.assert_allclose(closed.distance_m, 0.001, atol=1e-12)
    assert closed.coverage == 1.0 and closed.farthest_uncovered_m == pytest.approx(0.001)
    # without the closing side, the true side x = 0 is covered only within 3 mm of its
    # ends: (2 sqrt(3^2 - 1^2)) mm of its 100 mm
    assert open_.coverage == pytest.approx(0.75 + 2 * np.sqrt(8e-6) / 0.4, abs=1e-3)
    assert open_.farthest_uncovered_m == pytest.approx(np.hypot(0.05, 0.001))
    # two true pieces 100 mm apart: a point between them is 50 mm from both, not on a
    # segment joining them
    pieces = [square[:2], square[:2] + [0.0, 0.1, 0.0]]
    between = curve_agreement([[0.05, 0.05, 0.0]], pieces)
    assert between.max_m == pytest.approx(0.05)
    assert between.coverage == 0.0 and between.farthest_uncovered_m == np.inf
    with pytest.raises(ValueError, match=r'shape \(K, 3\)'):
        curve_agreement(np.zeros((4, 2)), square)
