"""Import graph of the rigctl package (every import, those inside functions included): prints the
module cycles and the imports that go up a layer. Usage: python3 tools/import_graph.py REPO_ROOT"""
import ast
import collections
import pathlib
import sys

ROOT = pathlib.Path(sys.argv[1])
DIRS = {"rigctl": "rigctl", "drivers": "rigctl.drivers", "emulators": "rigctl.emulators", "plans": "rigctl.plans"}
mods = {}
for d, pkg in DIRS.items():
    for f in (ROOT / d).rglob("*.py"):
        rel = f.relative_to(ROOT / d).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        mods[".".join([pkg, *parts])] = f
graph = collections.defaultdict(set); inner = collections.defaultdict(set)
for name, f in mods.items():
    tree = ast.parse(f.read_text())
    top = set(id(n) for n in tree.body)
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rigctl"):
            targets = [node.module] + [node.module + "." + a.name for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names if a.name.startswith("rigctl")]
        for t in targets:
            if t in mods and t != name:
                graph[name].add(t)
                if id(node) not in top and not (isinstance(node, ast.ImportFrom) and False):
                    inner[name].add(t)
# tarjan
index = {}; low = {}; stack = []; on = set(); sccs = []; c = [0]
sys.setrecursionlimit(10000)
def strong(v):
    index[v] = low[v] = c[0]; c[0] += 1; stack.append(v); on.add(v)
    for w in graph[v]:
        if w not in index: strong(w); low[v] = min(low[v], low[w])
        elif w in on: low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        s = []
        while True:
            w = stack.pop(); on.discard(w); s.append(w)
            if w == v: break
        if len(s) > 1: sccs.append(s)
for v in list(mods):
    if v not in index: strong(v)
print("module cycles:", len(sccs))
for s in sccs: print("  ", sorted(s))
# the rooms, lowest first: an import may only go to the same layer or one below (ARCHITECTURE.md)
LAYER = [("rigctl.__main__", 7), ("rigctl.apps", 5), ("rigctl.rigs", 4), ("rigctl.run", 3),
         ("rigctl.vision", 2), ("rigctl.emulators", 2), ("rigctl.plans", 2), ("rigctl.drivers", 1), ("rigctl.physics", 1),
         ("rigctl.core", 0), ("rigctl", 0)]
def layer(m):
    for p, l in LAYER:
        if m == p or m.startswith(p + "."): return l
ups = [(a, b) for a in graph for b in graph[a] if layer(b) > layer(a)]
print("upward imports:", len(ups))
for a, b in sorted(ups): print("  ", a, "->", b, "(in function)" if b in inner[a] else "")
