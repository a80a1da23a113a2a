#!/usr/bin/env python3
"""Fails when the modules of a crate import each other in a cycle, or when a folder of a layered crate
imports one above it.

For every crate of the workspace (each `Cargo.toml` with a `src/` beside it, `fuzz/` excluded), each source
file is a module (`lib.rs`/`main.rs` the root, `a/mod.rs` and `a.rs` the module `a`, `a/b.rs` the module
`a::b`). A file depends on another when it names it by a path: `use crate::a::b::{X, c::Y}`, `crate::a::f()`
in an expression, `super::x` and `self::x` resolved against the file's module (and the inline `mod` blocks
it is in). A path names the longest module it starts with; a name a module re-exports with `pub use` is
followed to the module that defines it. A module's uses of its own descendants are not edges (a parent
holds its children, and its `mod` lines and re-exports are how it shows them), nor are its `#[cfg(test)]`
modules' uses (tests sit above what they test). Every other cycle of the file graph is reported, with one
line per edge and where it is, and the script exits with 1.

The crates in `LAYERS` are layered: their top-level modules (folders and files under `src/`) are listed
from the bottom up, and a module may use only those in layers below its own. An import that runs up or
sideways (between two modules of one layer), or a top-level module missing from the list, is reported
with where it is, and the script exits with 1. No network, well under a second.
"""

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Per layered crate, its top-level modules from the bottom up; the modules of one layer do not use each
# other. The crate root (`lib.rs`) sits above them all.
LAYERS = {
    "runtime": [
        "error rng", "input whole_file", "json", "cameras", "data", "output", "field", "surfaces", "training", "volume", "splats",
    ],
    "lib": [
        "failure cluster city_model", "console", "interrupt", "observe", "script", "settings",
        "frame_files diagnostics folder_lock bake_file bake_view", "checkpoint", "training", "blocks", "session", "commands", "conformance",
    ],
}


def strip(text):
    """Blanks comments, strings and char literals (keeping newlines), so paths in them do not count."""
    out, i, n = [], 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "r" and re.match(r'r#*"', text[i:i + 8]) and not re.match(r"\w", text[i - 1:i] or " "):
            m = re.match(r'r(#*)"', text[i:])
            end = text.find('"' + m.group(1), i + len(m.group(0)))
            j = n if end < 0 else end + 1 + len(m.group(1))
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            out.append(re.sub(r"[^\n]", " ", text[i:j + 1]))
            i = j + 1
        elif c == "'":
            m = re.match(r"'(\\(x..|u\{[0-9a-fA-F]+\}|.)|[^\\'])'", text[i:i + 12])
            if m:  # a char literal, not a lifetime
                out.append(" " * len(m.group(0)))
                i += len(m.group(0))
            else:
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


def module_of(src, path):
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "mod" or (len(parts) == 1 and parts[0] in ("lib", "main")):
        parts = parts[:-1]
    return tuple(parts)


def expand_use(tree):
    """`a::{b, c::{d, e}}` → [a::b, a::c::d, a::c::e] (aliases and globs kept as the path before them)."""
    tree = re.sub(r"\s+", "", tree)
    brace = tree.find("{")
    if brace < 0:
        return [re.sub(r"(as\w+)$", "", tree.split(" as ")[0]).rstrip(":*")]
    prefix, inner = tree[:brace], tree[brace + 1:tree.rfind("}")]
    items, depth, start = [], 0, 0
    for k, ch in enumerate(inner):
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append(inner[start:k])
            start = k + 1
    items.append(inner[start:])
    paths = []
    for item in items:
        if not item:
            continue
        if item == "self":
            paths.append(prefix.rstrip(":"))
        else:
            paths.extend(prefix + p for p in expand_use(item))
    return paths


USE = re.compile(r"\b(pub(\([^)]*\))?\s+)?use\s+([^;]+);")
PATH = re.compile(r"(?<![\w:])((?:crate|super|self)(?:\s*::\s*\w+)+)")
MOD_BLOCK = re.compile(r"(#\[cfg\(test\)\]\s*)?(pub(\([^)]*\))?\s+)?mod\s+(\w+)\s*\{")


def scopes(text):
    """For each offset of `text`, the inline modules it is in: a list of (start, end, name, is_test)."""
    blocks = []
    for m in MOD_BLOCK.finditer(text):
        depth, j = 1, m.end()
        while j < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[j], 0)
            j += 1
        blocks.append((m.start(), j, m.group(4), bool(m.group(1))))
    return blocks


def crate_graph(src):
    files = sorted(p for p in src.rglob("*.rs"))
    modules = {}
    for f in files:
        modules.setdefault(module_of(src, f), f)
    texts = {m: strip(f.read_text()) for m, f in modules.items()}

    # Re-exports: (module, name) → the path it stands for.
    reexports = {}
    for mod, text in texts.items():
        for m in USE.finditer(text):
            if not m.group(1):
                continue
            for p in expand_use(m.group(3)):
                segs = p.split("::")
                alias = re.search(r"\bas\s+(\w+)", m.group(3))
                reexports[(mod, segs[-1])] = (mod, segs)
                if alias and len(expand_use(m.group(3))) == 1:
                    reexports[(mod, alias.group(1))] = (mod, segs)

    def absolute(mod, segs):
        if segs[0] == "crate":
            return list(segs[1:])
        base = list(mod)
        while segs and segs[0] in ("self", "super"):
            if segs[0] == "super":
                base = base[:-1]
            segs = segs[1:]
        return base + list(segs)

    def resolve(segs, seen=()):
        """The module defining the item `segs` names (absolute segments)."""
        k = len(segs)
        while k and tuple(segs[:k]) not in modules:
            k -= 1
        target = tuple(segs[:k])
        rest = segs[k:]
        if rest and (target, rest[0]) in reexports and (target, rest[0]) not in seen:
            where, path = reexports[(target, rest[0])]
            if path[0] in ("crate", "self", "super"):
                return resolve(absolute(where, path) + rest[1:], seen + ((target, rest[0]),))
            if path[0] in [m[-1] for m in modules if len(m) == len(where) + 1 and m[:-1] == where]:
                return resolve(list(where) + path + rest[1:], seen + ((target, rest[0]),))
        return target

    edges = {}
    for mod, text in texts.items():
        blocks = scopes(text)
        lines = text.count
        found, spans = [], []
        for m in USE.finditer(text):
            spans.append((m.start(), m.end()))
            for p in expand_use(m.group(3)):
                segs = p.split("::")
                if segs[0] in ("crate", "self", "super"):
                    found.append((m.start(), segs))
                elif segs[0] in [c[-1] for c in modules if c[:-1] == mod and len(c) == len(mod) + 1]:
                    found.append((m.start(), ["self"] + segs))  # `use child::X` in a parent
        for m in PATH.finditer(text):
            if any(a <= m.start() < b for a, b in spans):
                continue  # inside a `use` item: counted above
            found.append((m.start(), re.sub(r"\s+", "", m.group(1)).split("::")))
        for at, segs in found:
            inner = [b for b in blocks if b[0] <= at < b[1]]
            if any(b[3] for b in inner):
                continue
            here = mod + tuple(b[2] for b in sorted(inner))
            if segs[0] == "crate":
                target = resolve(segs[1:])
            else:
                target = resolve(absolute(here, segs))
            if target == mod or target[: len(mod)] == mod:
                continue  # itself, or one of its descendants
            line = lines("\n", 0, at) + 1
            edges.setdefault(mod, {}).setdefault(target, line)
    return modules, edges


def cycles(edges):
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    nodes = set(edges) | {t for ts in edges.values() for t in ts}

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def layering(crate, modules, edges):
    """Problems with the layers of `crate`: top-level modules without a layer, imports up or sideways."""
    layer_of = {m: k for k, layer in enumerate(LAYERS[crate]) for m in layer.split()}
    problems = [f"{crate}: top-level module '{top}' has no layer in LAYERS of .ci/check_cycles.py"
                for top in sorted({m[0] for m in modules if m} - set(layer_of))]
    for a, targets in sorted(edges.items()):
        for b, line in sorted(targets.items()):
            if not a or a[0] == (b[0] if b else None) or a[0] not in layer_of:
                continue
            where = modules[a].relative_to(ROOT)
            if not b:
                problems.append(f"{crate}: {name(a)} uses the crate root, which sits above every module ({where}:{line})")
                continue
            if b[0] not in layer_of:
                continue
            up, down = layer_of[a[0]], layer_of[b[0]]
            if down >= up:
                how = "up" if down > up else "sideways (one layer)"
                problems.append(f"{crate}: {name(a)} → {name(b)} runs {how}: '{a[0]}' is in layer {up}, "
                                f"'{b[0]}' in layer {down} ({where}:{line})")
    return problems


def name(mod):
    return "::".join(mod) or "crate"


def main():
    crates = sorted(
        p.parent / "src"
        for p in [ROOT / "Cargo.toml", *ROOT.glob("*/Cargo.toml")]
        if (p.parent / "src").is_dir() and "target" not in p.parts and "fuzz" not in p.relative_to(ROOT).parts
        and "node_modules" not in p.parts
    )
    failed = False
    for src in crates:
        modules, edges = crate_graph(src)
        crate = str(src.parent.relative_to(ROOT))
        if crate in LAYERS:
            for problem in layering(crate, modules, edges):
                failed = True
                print(problem)
        for comp in cycles(edges):
            failed = True
            crate = src.parent.relative_to(ROOT) or Path(".")
            print(f"{crate}: modules in an import cycle: {', '.join(name(m) for m in comp)}")
            members = set(comp)
            for a in comp:
                for b, line in sorted(edges.get(a, {}).items()):
                    if b in members:
                        where = modules[a].relative_to(ROOT)
                        print(f"    {name(a)} → {name(b)}  ({where}:{line})")
    if failed:
        sys.exit(1)
    print(f"no import cycles in the modules of {len(crates)} crates; {', '.join(LAYERS)} layered")


if __name__ == "__main__":
    main()
