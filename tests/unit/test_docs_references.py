"""The code's references into the specs resolve inside the repository: every
``ALGORITHMS.md §N.M`` names a section of docs/ALGORITHMS.md, every ``INTERFACES.md,
"Title"`` a section of docs/INTERFACES.md, and every ``docs/<file>`` exists."""

import re
from pathlib import Path

from harness import REPO_ROOT

DOCS = REPO_ROOT / 'docs'
SEARCHED = ('src', 'tests', 'bench', 'scripts')
THIS_FILE = Path(__file__).resolve()


def cited_files():
    for top in SEARCHED:
        for path in sorted((REPO_ROOT / top).rglob('*')):
            if (
                path.suffix in ('.py', '.md', '.yaml')
                and '__pycache__' not in path.parts
                and path != THIS_FILE
            ):
                yield path
    yield REPO_ROOT / 'README.md'


def headings(doc):
    return [
        line.lstrip('#').strip()
        for line in (DOCS / doc).read_text().splitlines()
        if line.startswith('#')
    ]


def citations(pattern):
    found = []
    for path in cited_files():
        for match in re.finditer(pattern, path.read_text(errors='replace')):
            found.append((path.relative_to(REPO_ROOT), ' '.join(match.group(1).split())))
    return found


def test_algorithms_sections_cited_in_the_code_exist():
    numbers = {h.split()[0].rstrip('.') for h in headings('ALGORITHMS.md')}
    cited = citations(r'ALGORITHMS\.md\s+§(\d+(?:\.\d+)*)')
    assert cited, 'no ALGORITHMS.md citation found: the pattern is stale'
    missing = [(str(path), number) for path, number in cited if number not in numbers]
    assert not missing, f'ALGORITHMS.md has no such section: {missing}'


def test_interfaces_sections_cited_in_the_code_exist():
    titles = headings('INTERFACES.md')
    cited = citations(r'INTERFACES\.md,?\s+"([^"]+)"')
    assert cited, 'no INTERFACES.md citation found: the pattern is stale'
    missing = [
        (str(path), title)
        for path, title in cited
        if not any(t.startswith(title) or title.startswith(t) for t in titles)
    ]
    assert not missing, f'INTERFACES.md has no such section: {missing}'


def test_cited_docs_files_exist():
    cited = citations(r'\bdocs/([A-Za-z_][\w.-]*\w)')
    missing = sorted({(str(path), name) for path, name in cited if not (DOCS / name).exists()})
    assert not missing, f'not in docs/: {missing}'


def test_cited_findings_exist():
    """``A4.4``, ``A-G1``: the findings list of docs/ALGORITHMS.md (the thesis's gaps and
    our resolutions), each a ``- **A4.4 ...**`` item there."""
    text = (DOCS / 'ALGORITHMS.md').read_text()
    defined = set(re.findall(r'^- \*\*(A\d+\.\d+|A-G\d+)\b', text, re.M))
    cited = citations(r'(?<![\w.])(A\d+\.\d+|A-G\d+)(?![\w.]*\d)')
    assert cited, 'no finding cited: the pattern is stale'
    missing = sorted({(str(path), tag) for path, tag in cited if tag not in defined})
    assert not missing, f'ALGORITHMS.md has no such finding: {missing}'


def test_no_reference_to_the_issue_tracker():
    """The tracker is not in the repository: code says what it means instead."""
    cited = citations(r'\b([Ii]ssue \d+)\b')
    assert not cited, f'references outside the repository: {cited}'
