#!/usr/bin/env python3
"""Prototypes of the identity methods compared in BENCHMARKS.md ("Identities", methods
compared), on the dumps of `identity_dump` (per frame: ids and every camera pair's raw
distances; the model's calibration): SPEC §3 pairwise, the union-find baseline, correlation
clustering (greedy additive edge contraction, camera-exclusive) on several affinities, and its
average-linkage variant; `--cameras` keeps a camera subset (the others' boxes removed),
`:VETO` adds the veto as a share of `t` (what ships: gaec:0.4:0.125:0.5; until 2026-12-04 gaec:0.35:0.125:0.25), `chains` prints how
often pairwise matching is intransitive, `--few` uses another setting on frames with at most N
cameras reporting. Scores identity-derived ACC / IPAA-100 exactly as `crossview eval`
(the pairwise and union-find rows reproduce the Rust figures to the last digit).

  cargo build --release -p crossview-bench --bin identity_dump
  target/release/identity_dump models/wildtrack-w64.onnx train.jsonl train_dump.jsonl
  python3 bench/identity_prototypes.py train_dump.jsonl [--cameras 0,1,2] [--few N:T:B:VETO] METHOD:T:B[:VETO] ... [chains]

METHOD: uf (union-find on S), gaec (max(S,P) links + support, min(0, P - t) elsewhere: what
ships), avg (the same weights, average linkage), dense (S - t on every entry), gated-s
(S - t on Hungarian pairs, min(0, S - t) elsewhere). Needs numpy and scipy
(bench/python_env.sh).
"""
import sys
import json, numpy as np
from scipy.optimize import linear_sum_assignment

def load(path):
    with open(path) as f:
        head = json.loads(f.readline())
        cal = head['calibration']
        frames = []
        for line in f:
            r = json.loads(line)
            ids = r['ids']
            sizes = [len(x) for x in ids]
            pairs = {}
            for p in r['pairs']:
                d = np.array(p['d'], dtype=np.float64).reshape(p['shape'])
                s = 1.0 - d / (d.max() + 1e-6)
                rows, cols = linear_sum_assignment(d)
                pairs[(p['a'], p['b'])] = dict(d=d, s=s, hung=list(zip(rows.tolist(), cols.tolist())))
            frames.append(dict(frame=r['frame'], ids=ids, sizes=sizes, pairs=pairs))
    return cal, frames

def prob(cal, d):
    xs, ps = np.array(cal['distances']), np.array(cal['probabilities'])
    return np.interp(d, xs, ps)

def add_prob(cal, frames):
    for fr in frames:
        for p in fr['pairs'].values():
            p['p'] = prob(cal, p['d'])

def subset(frames, cams):
    out = []
    cams = set(cams)
    for fr in frames:
        ids = [x if c in cams else [] for c, x in enumerate(fr['ids'])]
        pairs = {k: v for k, v in fr['pairs'].items() if k[0] in cams and k[1] in cams}
        out.append(dict(frame=fr['frame'], ids=ids, sizes=[len(x) for x in ids], pairs=pairs))
    return out

def score(frames, idents_list):
    """idents_list: per frame list of (conf, [(cam, i), ...]). Returns acc, ipaa100, deciles, ident precision."""
    tn_c = 0; union = 0; ok100 = 0; npairs = 0
    dec = np.zeros((10, 2))
    for fr, idents in zip(frames, idents_list):
        ids = fr['ids']
        where = {}
        for k, (conf, mem) in enumerate(idents):
            for m in mem:
                where[m] = k
        for (a, b), p in fr['pairs'].items():
            la, lb = ids[a], ids[b]
            L1, L2 = set(la), set(lb)
            un = len(L1 | L2)
            ma = [False]*len(la); mb = [False]*len(lb)
            corr = 0
            # identity-derived matches
            for i in range(len(la)):
                k = where.get((a, i))
                for (c, j) in idents[k][1]:
                    if c == b:
                        ma[i] = True; mb[j] = True
                        corr += la[i] == lb[j]
            tn = sum(1 for i in range(len(la)) if not ma[i] and la[i] not in L2) + \
                 sum(1 for j in range(len(lb)) if not mb[j] and lb[j] not in L1)
            good = tn + corr
            tn_c += good; union += un; ok100 += good >= un; npairs += 1
        cnt = {}
        for c, x in enumerate(ids):
            for g in x: cnt[g] = cnt.get(g, 0) + 1
        for conf, mem in idents:
            g = ids[mem[0][0]][mem[0][1]]
            right = all(ids[c][i] == g for c, i in mem) and cnt[g] == len(mem)
            k = min(int(max(0.0, min(1.0, conf)) * 10), 9)
            dec[k, 0] += 1; dec[k, 1] += right
    return 100*tn_c/union, 100*ok100/npairs, dec

def monotone(dec, tol=3.0):
    prec = [100*c/n if n else None for n, c in dec]
    last = None; ok = True
    for p in prec:
        if p is None: continue
        if last is not None and p < last - tol: ok = False
        last = p if last is None else max(last, p) if False else p
    return ok

def fmt_dec(dec):
    return ' '.join(f"{k/10:.1f}:{100*c/n:.0f}%/{int(n)}" for k, (n, c) in enumerate(dec) if n)



def boxes(fr):
    nodes = [(c, i) for c, k in enumerate(fr['sizes']) for i in range(k)]
    idx = {m: n for n, m in enumerate(nodes)}
    return nodes, idx

def dense(fr, key):
    nodes, idx = boxes(fr)
    n = len(nodes)
    A = np.full((n, n), np.nan)
    H = np.zeros((n, n), bool)
    for (a, b), p in fr['pairs'].items():
        ia = [idx[(a, i)] for i in range(fr['sizes'][a])]
        ib = [idx[(b, j)] for j in range(fr['sizes'][b])]
        M = p[key]
        A[np.ix_(ia, ib)] = M; A[np.ix_(ib, ia)] = M.T
        for (i, j) in p['hung']:
            H[ia[i], ib[j]] = H[ib[j], ia[i]] = True
    return nodes, A, H

def union_find(fr, t, bonus, key='s'):
    nodes, A, H = dense(fr, key)
    n = len(nodes)
    cam = np.array([c for c, _ in nodes])
    ncam = len(fr['sizes'])
    # Hungarian partner per camera (kept only)
    part = -np.ones((n, ncam), int)
    for u in range(n):
        for v in np.nonzero(H[u])[0]:
            if A[u, v] >= t: part[u, cam[v]] = v
    edges = []
    for u in range(n):
        for v in np.nonzero(H[u])[0]:
            if v > u and A[u, v] >= t:
                agree = sum(1 for c in range(ncam) if c != cam[u] and c != cam[v] and part[u, c] >= 0 and part[u, c] == part[v, c])
                edges.append((A[u, v] + bonus * agree, u, v))
    edges.sort(key=lambda e: (-e[0], e[1], e[2]))
    root = list(range(n)); cams = [{cam[u]} for u in range(n)]
    def find(x):
        while root[x] != x:
            root[x] = root[root[x]]; x = root[x]
        return x
    for w, u, v in edges:
        r, s = find(u), find(v)
        if r == s or cams[r] & cams[s]: continue
        root[s] = r; cams[r] |= cams[s]
    cl = {}
    for u in range(n): cl.setdefault(find(u), []).append(u)
    return nodes, A, H, list(cl.values())

def gaec(fr, W, nodes, veto=-np.inf):
    """Greedy additive edge contraction with camera exclusivity on weight matrix W (nan = same
    camera or no evidence); two clusters never merge while a pair of their boxes weighs below
    `veto` (the shipped veto: -t/4)."""
    n = len(nodes)
    if n == 0: return []
    cam = np.array([c for c, _ in nodes])
    Wc = np.where(np.isnan(W), 0.0, W).copy()
    Wmin = np.where(np.isnan(W), np.inf, W).copy()
    conf = cam[:, None] == cam[None, :]
    alive = np.ones(n, bool)
    members = [[u] for u in range(n)]
    while True:
        M = np.where(conf | ~alive[None, :] | ~alive[:, None] | (Wmin < veto), -np.inf, Wc)
        np.fill_diagonal(M, -np.inf)
        k = np.argmax(M)
        r, s = divmod(k, n)
        if not M[r, s] > 0: break
        if s < r: r, s = s, r
        Wc[r] += Wc[s]; Wc[:, r] += Wc[:, s]
        Wmin[r] = np.minimum(Wmin[r], Wmin[s]); Wmin[:, r] = np.minimum(Wmin[:, r], Wmin[:, s])
        conf[r] |= conf[s]; conf[:, r] |= conf[:, s]
        alive[s] = False
        members[r] += members[s]
    return [sorted(members[u]) for u in range(n) if alive[u]]

def as_idents(nodes, clusters, confs):
    out = []
    for cl, c in sorted(zip(clusters, confs), key=lambda x: x[0][0]):
        out.append((c, [nodes[u] for u in cl]))
    return out


def weights(fr, kind, t, b):
    nodes, A, H = dense(fr, 's')
    _, P, _ = dense(fr, 'p')
    n, ncam = len(nodes), len(fr['sizes'])
    cam = np.array([c for c, _ in nodes], dtype=int)
    if kind == 'dense':
        return nodes, A - t
    if kind == 'gated-s':
        return nodes, np.where(H, A - t, np.minimum(0, A - t))
    part = -np.ones((n, ncam), int)
    us, vs = np.nonzero(H)
    part[us, cam[vs]] = vs
    W = np.where(H, np.maximum(A, P) - t, np.minimum(0, P - t))
    for u, v in zip(us, vs):
        W[u, v] += b * np.sum((part[u] >= 0) & (part[u] == part[v]))
    return nodes, W


def gaec_avg(W, nodes):
    """Average linkage: merge the camera-disjoint pair with the largest mean weight while > 0."""
    n = len(nodes)
    if n == 0:
        return []
    cam = np.array([c for c, _ in nodes], dtype=int)
    Wc = np.where(np.isnan(W), 0.0, W).copy()
    size = np.ones(n)
    conf = cam[:, None] == cam[None, :]
    alive = np.ones(n, bool)
    members = [[u] for u in range(n)]
    while True:
        M = np.where(conf | ~alive[None, :] | ~alive[:, None], -np.inf,
                     Wc / (size[:, None] * size[None, :]))
        np.fill_diagonal(M, -np.inf)
        r, s = divmod(int(np.argmax(M)), n)
        if not M[r, s] > 0:
            break
        r, s = min(r, s), max(r, s)
        Wc[r] += Wc[s]; Wc[:, r] += Wc[:, s]; size[r] += size[s]
        conf[r] |= conf[s]; conf[:, r] |= conf[:, s]
        alive[s] = False; members[r] += members[s]
    return [sorted(members[u]) for u in range(n) if alive[u]]


def run(frames, method, t, b, veto=None, few=None):
    """`veto`: share of `t` (the shipped ¼); None = no veto. `few`: (N, t, b, veto) used instead
    on frames with at most N cameras reporting (a rule by camera count)."""
    res = []
    outer = (t, b, veto)
    for fr in frames:
        t, b, veto = outer
        if few is not None and sum(1 for k in fr['sizes'] if k > 0) <= few[0]:
            t, b, veto = few[1:]
        if method == 'uf':
            nodes, _, _, cl = union_find(fr, t, b, 's')
        else:
            nodes, W = weights(fr, method, t, b)
            level = -np.inf if veto is None else -veto * t
            cl = gaec_avg(W, nodes) if method == 'avg' else gaec(fr, W, nodes, level)
        res.append(as_idents(nodes, cl, [0.5] * len(cl)))
    return score(frames, res)


def chains(frames, thr=0.5):
    """Pairwise `S >= thr` matching's transitivity: chains A-B-C it matches, and how many of
    them have A-C not matched to the same box."""
    total = broken = 0
    for fr in frames:
        m = {k: {i: j for i, j in p['hung'] if p['s'][i, j] >= thr} for k, p in fr['pairs'].items()}
        cams = [c for c, k in enumerate(fr['sizes']) if k > 0]
        for x, a in enumerate(cams):
            for y, b in enumerate(cams[x + 1:], x + 1):
                for c in cams[y + 1:]:
                    ab, bc, ac = m.get((a, b), {}), m.get((b, c), {}), m.get((a, c), {})
                    for i, j in ab.items():
                        if j in bc:
                            total += 1
                            broken += ac.get(i) != bc[j]
    return total, broken


if __name__ == '__main__':
    args = sys.argv[1:]
    cameras = None
    if '--cameras' in args:
        k = args.index('--cameras')
        cameras = [int(c) for c in args[k + 1].split(',')]
        del args[k:k + 2]
    few = None
    if '--few' in args:
        k = args.index('--few')
        n, *rest = args[k + 1].split(':')
        few = (int(n), *map(float, rest))
        del args[k:k + 2]
    cal, frames = load(args[0])
    if cal:
        add_prob(cal, frames)
    if cameras is not None:
        frames = subset(frames, cameras)
    for arg in args[1:]:
        if arg == 'chains':
            total, broken = chains(frames)
            print(f"pairwise S>=0.5 chains A-B-C: {total}, A-C not the same box: {broken} "
                  f"({100 * broken / max(total, 1):.1f} %)", flush=True)
            continue
        m, t, b, *v = arg.split(':')
        veto = float(v[0]) if v else None
        acc, ipaa, _ = run(frames, m, float(t), float(b), veto, few)
        print(f"{arg}: ACC {acc:.2f} IPAA-100 {ipaa:.2f}", flush=True)
