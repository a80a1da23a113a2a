#!/usr/bin/env python3
"""Checks the documentation without building anything: every relative link and image in README.md and
docs/*.md names a file (or folder) of the repository, every #anchor a heading of the page it points to, and
README.md stays a front door of at most 200 lines. Exit status 1 and one line per problem otherwise."""
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_README_LINES = 200
LINK = re.compile(r'!?\[(?:[^\]\\]|\\.)*\]\(([^)\s]+)(?:\s+"[^"]*")?\)|<img\s[^>]*?src="([^"]+)"')


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
    count = len((ROOT / 'README.md').read_text(encoding='utf-8').rstrip('\n').split('\n'))
    if count > MAX_README_LINES:
        problems.append(f'README.md: {count} lines, more than {MAX_README_LINES}: move details into docs/')
    for p in problems:
        print(p)
    print(f'docs: {len(pages)} pages checked, {len(problems)} problems', file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
