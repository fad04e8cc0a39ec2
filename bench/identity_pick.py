#!/usr/bin/env python3
"""The identity step's selection rule (BENCHMARKS.md, "Identities"): reads the `identity_sweep`
grid tables that bench/identity_sweep.sh writes for each model on the WILDTRACK training frames
(grid_MODEL.md) and for the square4 presets (grid_sq1.md … grid_sq3.md), keeps the settings whose
sparse presets all reach ACC ≥ 99, and ranks them by the mean over the models of ACC + IPAA-100.
Also prints, per setting, the worst margin over pairwise (ACC or IPAA-100, any model) and on how
many models the confidence deciles are monotone.

usage: bench/identity_pick.py DIR MODEL... [--all] (DIR holds the grid tables)
"""
import sys


def read(path):
    pairwise, rows = None, {}
    for line in open(path):
        c = [x.strip() for x in line.split('|')]
        if len(c) < 9:
            continue
        if c[1].startswith('pairwise'):
            pairwise = (float(c[5]), float(c[6]))
        elif c[1] == 'clustering':
            rows[(c[2], c[3], c[4])] = (float(c[5]), float(c[6]), c[8] == 'yes')
    return pairwise, rows


def main():
    args = [a for a in sys.argv[1:] if a != '--all']
    show_all = '--all' in sys.argv
    d, models = args[0], args[1:]
    sparse = ['sq1', 'sq2', 'sq3']
    tables = {m: read(f'{d}/grid_{m}.md') for m in models + sparse}
    ranked = []
    for k in tables[models[0]][1]:
        ok = all(tables[s][1][k][0] >= 99 for s in sparse)
        per = [tables[m][1][k][0] + tables[m][1][k][1] for m in models]
        margin = min(min(tables[m][1][k][0] - tables[m][0][0], tables[m][1][k][1] - tables[m][0][1])
                     for m in models)
        mono = sum(tables[m][1][k][2] for m in models)
        ranked.append((sum(per) / len(per), k, ok, per, margin, mono))
    ranked.sort(key=lambda r: -r[0])
    print('| t | b | veto | square4 ≥ 99 | mean ACC + IPAA-100 | per model (' + ', '.join(models)
          + ') | worst margin over pairwise | deciles monotone |')
    print('|---:|---:|---:|---|---:|---|---:|---:|')
    for score, (t, b, v), ok, per, margin, mono in ranked:
        if ok or show_all:
            print(f"| {t} | {b} | {v} | {'yes' if ok else 'no'} | {score:.2f} | "
                  f"{' / '.join(f'{x:.1f}' for x in per)} | {margin:+.2f} | {mono}/{len(models)} |")


if __name__ == '__main__':
    main()
