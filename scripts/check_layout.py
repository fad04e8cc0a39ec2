#!/usr/bin/env python3
"""The workspace's layout rules, read from the code (no build needed).

1. No import circle between the modules of a crate: module A uses module B (`use crate::b`,
   `use super::b`, or a `crate::b::...` path in the code) and B, directly or through others,
   uses A. A module and the modules inside it are one unit here (a child using its parent's
   items is not a circle).
2. The layers of crossview-serve: transports -> service -> scene -> core. Cross-cutting
   modules (error, config, auth, body, conn, tls, metrics, locks, echo) import no domain
   module and no transport; domain modules (sync, cost, scene, registry, reload, record, subscribers,
   service) import no transport and not the router; only the router and the crate root bind
   the transports (the one exception: `config` holds the Kafka transport's settings type).
3. Sizes (reported; `--strict-sizes` fails on them): no non-test source file over 600 lines
   and no function over 100 lines in crossview-serve, crossview-core and crossview-train.

Usage: python3 scripts/check_layout.py [--strict-sizes]   (exit 1 on a violation)
"""
import argparse
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
CRATES = {p.parent.name if p.parent.name != "src" else p.parent.parent.name: p.parent
          for p in list(ROOT.glob("crates/*/src/lib.rs")) + [ROOT / "src/lib.rs",
                                                              ROOT / "loadtest/src/main.rs"]}
SIZED = ["serve", "core", "train"]
# crossview-serve's layers: a module of a layer may import its own layer and those listed.
CROSS = {"error", "auth", "body", "conn", "tls", "metrics", "locks", "echo"}
# `config` assembles every settings type (the domain's, and the Kafka transport's).
SETTINGS = {"config"}
DOMAIN = {"sync", "cost", "scene", "registry", "reload", "record", "heal", "subscribers", "service"}
TOP = {"router", ""}  # the crate root binds everything
ALLOWED_UP = {(("config",), ("transport", "kafka", "config"))}


def layer_violation(mod: tuple, dep: tuple) -> bool:
    """True when serve module `mod` may not import `dep`."""
    if (mod[:1], dep[:3]) in ALLOWED_UP or (mod, dep) in ALLOWED_UP:
        return False
    top, target = (mod[0] if mod else ""), (dep[0] if dep else "")
    if top in TOP:
        return False
    if top == "transport":
        return target in TOP
    if top in DOMAIN | SETTINGS:
        return target in TOP or target == "transport"
    if top in CROSS:
        return target in TOP or target == "transport" or target in DOMAIN
    return False
MAX_FILE, MAX_FN = 600, 100

USE = re.compile(r"\b(?:crate|super)(?:::\w+)+")
FN = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(?:async\s+)?(?:const\s+)?(?:unsafe\s+)?fn\s+(\w+)")


def modules(src: pathlib.Path):
    """Module path (tuple) -> file, for every .rs file under `src` except test modules."""
    out = {}
    for f in src.rglob("*.rs"):
        rel = f.relative_to(src).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] in ("lib", "main", "mod"):
            parts = parts[:-1]
        if parts and parts[-1] == "tests" or "bin" in parts[:1]:
            continue
        out[tuple(parts)] = f
    return out


def strip_tests(text: str) -> str:
    """The text up to a `#[cfg(test)]` module (tests may import anything)."""
    m = re.search(r"^#\[cfg\(test\)\]\s*\n\s*mod\s+\w+\s*\{", text, re.M)
    return text[: m.start()] if m else text


def uses(mod: tuple, text: str, known: dict):
    """The modules `mod` refers to through `crate::` / `super::` paths."""
    found = set()
    code = re.sub(r"//.*", "", strip_tests(text))
    # `use crate::{a, b::c}` groups: expand the first level.
    for m in re.finditer(r"\buse\s+(crate|super)::\{([^;]*)\};", code, re.S):
        for item in re.split(r",", m.group(2)):
            item = item.strip().split("::")[0].split(" ")[0].strip("{} \n")
            if item:
                code += f"\n{m.group(1)}::{item}"
    for m in USE.finditer(code):
        parts = m.group(0).split("::")
        base = list(mod)
        if parts[0] == "crate":
            base, rest = [], parts[1:]
        else:
            rest = parts
            while rest and rest[0] == "super":
                base = base[:-1]
                rest = rest[1:]
        path = base + rest
        # The longest known module prefix.
        for n in range(len(path), -1, -1):
            if tuple(path[:n]) in known:
                found.add(tuple(path[:n]))
                break
    return found


def unit(mod: tuple, other: tuple) -> bool:
    """True when one module contains the other."""
    n = min(len(mod), len(other))
    return mod[:n] == other[:n]


def circles(graph: dict):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                out.append(comp)

    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    return out


def long_functions(text: str):
    """(name, first line, lines) of every function longer than MAX_FN lines (outside tests)."""
    lines = strip_tests(text).splitlines()
    out = []
    for i, line in enumerate(lines):
        m = FN.match(line)
        if not m or line.rstrip().endswith(";"):
            continue
        depth, started = 0, False
        for j in range(i, len(lines)):
            depth += lines[j].count("{") - lines[j].count("}")
            started |= "{" in lines[j]
            if started and depth <= 0:
                if j - i + 1 > MAX_FN:
                    out.append((m.group(1), i + 1, j - i + 1))
                break
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--strict-sizes", action="store_true")
    args = ap.parse_args()
    failed = False
    for crate, src in sorted(CRATES.items()):
        mods = modules(src)
        graph = {m: set() for m in mods}
        for m, f in mods.items():
            for d in uses(m, f.read_text(), mods):
                if d != m and not unit(m, d):
                    graph[m].add(d)
        for comp in circles(graph):
            failed = True
            names = ", ".join("::".join(c) or "(root)" for c in sorted(comp))
            print(f"{crate}: import circle between {names}")
        if crate == "serve":
            for m in sorted(graph):
                for d in sorted(graph[m]):
                    if layer_violation(m, d):
                        failed = True
                        print(f"serve: {'::'.join(m)} imports {'::'.join(d) or '(root)'}, "
                              "a higher layer")
    sizes = []
    for crate in SIZED:
        src = CRATES.get(crate)
        if src is None:
            continue
        for f in sorted(src.rglob("*.rs")):
            if f.name == "tests.rs" or "tests" in f.relative_to(src).parts:
                continue
            text = f.read_text()
            n = len(strip_tests(text).splitlines())
            rel = f.relative_to(ROOT)
            if n > MAX_FILE:
                sizes.append(f"{rel}: {n} lines (over {MAX_FILE})")
            for name, line, length in long_functions(text):
                sizes.append(f"{rel}:{line}: fn {name} is {length} lines (over {MAX_FN})")
    for s in sizes:
        print(("" if args.strict_sizes else "note: ") + s)
    if sizes and args.strict_sizes:
        failed = True
    print("layout: " + ("violations found" if failed else
                        f"no import circles in {len(CRATES)} crates, serve's layers hold; "
                        f"{len(sizes)} size notes"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
