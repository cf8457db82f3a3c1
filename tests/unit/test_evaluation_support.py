"""What the benches share: a table has its header and rule, each result lands as Markdown
and JSON (numpy values included), a row that does not fit its header is refused; the
disparity measures count only the pixels known in both maps."""

import json

import numpy as np
import pytest
from vgm_evaluation.bench_report import markdown_table, write_results
from vgm_evaluation.metrics import disparity_agreement


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
