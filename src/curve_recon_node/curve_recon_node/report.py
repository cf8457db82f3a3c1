"""What curve_recon_node says about a reconstruction and about its state, without ROS:
the diagnostic's level, message and values (the node publishes and logs them)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from curve_recon_node.pipeline import Reconstruction


def reconstruction_report(
    result: Reconstruction,
    names: Sequence[str],
    stamp_ns: int,
    normals_source: str,
    settings: Mapping[str, Any],
) -> tuple[str, str, dict[str, Any]]:
    """(level, message, values) of the 'reconstruction' diagnostic of ``result`` from the
    cameras ``names``; ``settings`` adds its values (method, degree). Two views warn when
    samples were ambiguous (the third view would have chosen)."""
    stats = result.stats
    shape = 'closed loop' if result.closed else 'open curve'
    message = (
        f'published {len(result.waypoints_base)} waypoints ({shape}, '
        f'{stats["length_m"]:.2f} m) from {len(names)} views in {stats["time_ms"]:.0f} ms'
    )
    values = dict(
        stats,
        normals=normals_source,
        stamp_ns=stamp_ns,
        **settings,
        stage_ms=', '.join(f'{stage} {ms:.1f}' for stage, ms in stats['stage_ms'].items()),
    )
    level = 'warn' if len(names) == 2 and stats.get('ambiguous') else 'ok'
    if len(names) == 2:
        message += f'; two views only: {stats.get("ambiguous", 0)} samples ambiguous and dropped'
    return level, message, values


def capture_status(
    uncalibrated: Sequence[str], views: int, unsynchronized: int, published: bool
) -> tuple[str, str]:
    """(level, message) of the 'status' diagnostic: waiting for the calibration of the
    cameras ``views`` needs among ``uncalibrated``, images whose stamps do not agree
    (``unsynchronized`` dropped since the last capture), or all well."""
    needed = [n for n in uncalibrated if n in ('left', 'right') or (n == 'aux' and views == 3)]
    if needed:
        return 'warn', f'no camera info yet: waiting for the calibration of {", ".join(needed)}'
    if unsynchronized:
        return 'warn', (
            f'images not synchronized: {unsynchronized} dropped since the last complete '
            'capture (stamps must be identical)'
        )
    return 'ok', 'waypoints published' if published else 'waiting for a capture'
