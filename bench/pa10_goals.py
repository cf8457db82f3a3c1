"""The goals every pa10_ik_node bench part judges a finished case by (bench_pa10_ik.py,
pa10_ik_topics.py)."""

GOALS = {
    'rms_mm': 0.05,
    'passed_fraction': 0.99,
    'force_p95_pct': 3.0,
    'step_ms_median': 1.0,
    'stop_latency_ms': 10.0,
}


def meets_goals(row):
    """Which of the issue's goals a finished case misses ([] = all met)."""
    missed = []
    if row['phase'] != 'done' or row['stage'] != 'lifted':
        return [f'ended {row["phase"]}: {row["reason"]}']
    if not row['rms_mm'] < GOALS['rms_mm']:
        missed.append(f'rms {row["rms_mm"]:.3f} mm')
    if not row['passed_fraction'] > GOALS['passed_fraction']:
        missed.append(f'passed {row["passed_fraction"] * 100:.1f} %')
    if not row['force_p95_pct'] < GOALS['force_p95_pct']:
        missed.append(f'force p95 {row["force_p95_pct"]:.2f} %')
    if row['velocity_ratio'] > 1 + 1e-9 or row['limit_margin_rad'] < 0:
        missed.append('a joint limit')
    return missed
