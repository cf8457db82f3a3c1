#!/usr/bin/env python3
"""make bench: run every bench/bench_*.py in turn; each writes its results to
bench/results/."""

import subprocess
import sys
from pathlib import Path

failed = []
for script in sorted(Path(__file__).resolve().parent.glob('bench_*.py')):
    print(f'\n== {script.name}', flush=True)
    if subprocess.run([sys.executable, str(script)]).returncode != 0:
        failed.append(script.name)
if failed:
    sys.exit(f'benchmarks failed: {", ".join(failed)}')
