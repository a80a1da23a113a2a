#!/usr/bin/env python3
"""Checks the documentation without building anything. Exit status 1 and one line per problem otherwise.

- Links: every relative link and image in README.md and docs/*.md names a file (or folder) of the repository,
  and every #anchor a heading of the page it points to.
- The README stays a front door: at most 200 lines, none longer than 300 characters (table rows included).
- Docs state what is true now; a dated log belongs in one page, docs/LOG.md. Every other page (README.md and
  docs/*.md) holds at most 6 dated lines, a dated line being one with a date written YYYY-MM-DD outside a link's
  target: enough for the lines that say when each current table was measured (RESULTS.md and BENCHMARKS.md give
  them in one table of sittings), not for a history.
- docs/BENCHMARKS.md and docs/RESULTS.md hold the method and the current tables: at most 450 lines each.
- An example's header (the `//` lines before its first other line) says what the example does in at most 5
  lines and holds no date: measurements go to docs/RESULTS.md, their history to docs/LOG.md.
"""
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_README_LINES = 200
MAX_README_CHARS = 300
MAX_DATED_LINES = 6
LOG_PAGE = 'docs/LOG.md'
MAX_CURRENT_PAGE_LINES = {'docs/BENCHMARKS.md': 450, 'docs/RESULTS.md': 450}
MAX_EXAMPLE_HEADER_LINES = 5
LINK = re.compile(r'!?\[(?:[^\]\\]|\\.)*\]\(([^)\s]+)(?:\s+"[^"]*")?\)|<img\s[^>]*?src="([^"]+)"')
DATE = re.compile(r'\b\d{4}-\d{2}-\d{2}\b')
LINK_TARGET = re.compile(r'\]\([^)]*\)')


def slug(heading):
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r'`|\*\*|\[([^\]]*)\]\([^)]*\)', r'\1', heading.strip()).lower()
    text = ''.join(c for c in text if c.isalnum() or c in ' -_')
    return text.replace(' ', '-')


def anchors(path):
    seen, out = {}, set()
    in_code = False
    for line in path.read_text(encoding='utf-8').split('\n'):
        if line.startswith('```'):
            in_code = not in_code
        elif not in_code and re.match(r'#{1,6} ', line):
            s = slug(line.lstrip('#'))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f'{s}-{n}')
    return out


def links(path):
    in_code = False
    for number, line in enumerate(path.read_text(encoding='utf-8').split('\n'), 1):
        if line.startswith('```'):
            in_code = not in_code
            continue
        if in_code:
            continue
        for m in LINK.finditer(re.sub(r'`[^`]*`', '', line)):
            yield number, m.group(1) or m.group(2)


def page_lines(path):
    return path.read_text(encoding='utf-8').rstrip('\n').split('\n')


def dated_lines(path):
    """The numbers of the lines that hold a date outside a link's target."""
    return [n for n, line in enumerate(page_lines(path), 1) if DATE.search(LINK_TARGET.sub('](', line))]


def example_header(path):
    header = []
    for line in page_lines(path):
        if not line.startswith('//'):
            break
        header.append(line)
    return header


def main():
    problems = []
    pages = [ROOT / 'README.md'] + sorted((ROOT / 'docs').glob('*.md'))
    for page in pages:
        for number, target in links(page):
            if re.match(r'[a-z][a-z0-9+.-]*:', target):  # https:, mailto:
                continue
            file, _, anchor = target.partition('#')
            dest = (page.parent / file).resolve() if file else page
            where = f'{page.relative_to(ROOT)}:{number}'
            if not dest.exists():
                problems.append(f'{where}: {target}: no such file')
            elif anchor and dest.suffix == '.md' and anchor not in anchors(dest):
                problems.append(f'{where}: {target}: no heading #{anchor} in {dest.relative_to(ROOT)}')

    readme = page_lines(ROOT / 'README.md')
    if len(readme) > MAX_README_LINES:
        problems.append(f'README.md: {len(readme)} lines, more than {MAX_README_LINES}: move details into docs/')
    for number, line in enumerate(readme, 1):
        if len(line) > MAX_README_CHARS:
            problems.append(f'README.md:{number}: {len(line)} characters, more than {MAX_README_CHARS}: '
                            'one current figure a row, details in docs/')

    for page in pages:
        name = page.relative_to(ROOT).as_posix()
        if name == LOG_PAGE:
            continue
        dated = dated_lines(page)
        if len(dated) > MAX_DATED_LINES:
            shown = ', '.join(str(n) for n in dated[:8]) + (', …' if len(dated) > 8 else '')
            problems.append(f'{name}: {len(dated)} dated lines (lines {shown}), more than {MAX_DATED_LINES}: '
                            f'the history goes to {LOG_PAGE}')
    for name, limit in MAX_CURRENT_PAGE_LINES.items():
        count = len(page_lines(ROOT / name))
        if count > limit:
            problems.append(f'{name}: {count} lines, more than {limit}: keep the method and the current tables, '
                            f'move the history to {LOG_PAGE}')

    for example in sorted((ROOT / 'examples').glob('*.sdf')):
        name = example.relative_to(ROOT).as_posix()
        header = example_header(example)
        if len(header) > MAX_EXAMPLE_HEADER_LINES:
            problems.append(f'{name}: a header of {len(header)} comment lines, more than '
                            f'{MAX_EXAMPLE_HEADER_LINES}: say what the example does, point to docs/RESULTS.md')
        for number, line in enumerate(header, 1):
            if DATE.search(line):
                problems.append(f'{name}:{number}: a date in the header: measurements go to docs/RESULTS.md')

    for p in problems:
        print(p)
    print(f'docs: {len(pages)} pages and the examples\' headers checked, {len(problems)} problems', file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
