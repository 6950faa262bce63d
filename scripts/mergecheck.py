"""Merge-rule analysis over a `silvr reconstruct` output: which submap should keep a contested voxel?

    python3 scripts/mergecheck.py OUT WORLD [points_filtered.ply | points.ply]

OUT: a reconstruct folder (train/submap_*/points*.ply, submaps/submap_*/transforms.json); WORLD: the synthetic
world it came from (gt/cloud.ply). In every 0.2 m voxel that several submaps' points share, each candidate rule
picks one submap; printed: the mean distance to GT of the kept points, beside the oracle and the worst pick.
Distances are in the reconstruct's frame (the poses stage's; near the world's when its poses are exact).
Needs numpy and scipy (an analysis script, not a product dependency). BENCHMARKS.md, issue 19, has results."""
import json, sys, glob, os
import numpy as np
from scipy.spatial import cKDTree

T = {'double': 'f8', 'float': 'f4', 'uchar': 'u1', 'uint8': 'u1', 'int': 'i4', 'uint': 'u4', 'float32': 'f4', 'float64': 'f8', 'int32': 'i4', 'uint32': 'u4', 'short': 'i2', 'ushort': 'u2'}

def read_ply(p):
    f = open(p, 'rb')
    props, n = [], 0
    while True:
        line = f.readline().decode().strip()
        if line.startswith('element vertex'):
            n = int(line.split()[-1])
        elif line.startswith('property'):
            _, t, name = line.split()
            props.append((name, '<' + T[t]))
        elif line == 'end_header':
            break
    return np.frombuffer(f.read(), dtype=np.dtype(props), count=n)

out = sys.argv[1]
world = sys.argv[2]
voxel = 0.2
gt = read_ply(f'{world}/gt/cloud.ply')
tree = cKDTree(np.stack([gt['x'], gt['y'], gt['z']], 1))
subs = sorted(glob.glob(f'{out}/train/submap_*')) or sorted(glob.glob(f'{out}/*/submap_*'))
print('submaps', subs)
P, S, L, Q, D, C = [], [], [], [], [], []
cams = []
for k, d in enumerate(subs):
    c = read_ply(f'{d}/' + (sys.argv[3] if len(sys.argv) > 3 else 'points_filtered.ply'))
    xyz = np.stack([c['x'], c['y'], c['z']], 1).astype(np.float64)
    ls = c['log_std_combined'].astype(np.float64)
    pct = np.argsort(np.argsort(ls)) / max(len(ls) - 1, 1)
    dist, _ = tree.query(xyz)
    P.append(xyz); S.append(np.full(len(xyz), k)); L.append(ls); Q.append(pct); D.append(dist)
    name = os.path.basename(d)
    tj = json.load(open(glob.glob(f'{out}/submaps/{name}/transforms.json')[0]))
    train = set(tj.get('train_filenames') or [])
    fr = [f for f in tj['frames'] if not train or f['file_path'] in train]
    cams.append(np.array([np.array(f['transform_matrix'])[:3, 3] for f in fr]))
P = np.concatenate(P); S = np.concatenate(S); L = np.concatenate(L); Q = np.concatenate(Q); D = np.concatenate(D)
camd = np.stack([cKDTree(c).query(P)[0] for c in cams], 1)  # point to each submap's nearest camera
vox = np.floor(P / voxel).astype(np.int64)
_, vid = np.unique(vox, axis=0, return_inverse=True)
vid = vid.ravel()
nv = vid.max() + 1
ns = len(subs)
# Per (voxel, submap): count, sum of GT distance, median stats approximated by means.
key = vid * ns + S
cnt = np.bincount(key, minlength=nv * ns).reshape(nv, ns)
def per(v, agg=np.median):
    out = np.full(nv * ns, np.nan)
    order = np.argsort(key, kind='stable')
    ks, starts = np.unique(key[order], return_index=True)
    for kk, a, b in zip(ks, starts, list(starts[1:]) + [len(order)]):
        out[kk] = agg(v[order[a:b]])
    return out.reshape(nv, ns)
dmean = per(D, np.mean)
lmed = per(L)
qmed = per(Q)
cmed = per(camd[np.arange(len(P)), S])
contested = (cnt > 0).sum(1) >= 2
print(f'voxels {nv}, contested {contested.sum()}')
cs = np.where(contested)[0]
def score(choice):
    # mean GT distance over the kept points of contested voxels (point-weighted)
    k = cnt[cs, choice]
    return float((dmean[cs, choice] * k).sum() / k.sum())
inf = np.where(cnt[cs] > 0, 0, np.inf)
rules = {
    'raw log-std (current)': np.nanargmin(lmed[cs] + inf, 1),
    'log-std percentile in own submap': np.nanargmin(qmed[cs] + inf, 1),
    'nearest training camera': np.nanargmin(cmed[cs] + inf, 1),
    'log-std z-score in own submap': None,
    'percentile + camera rank': None,
    'oracle (best)': np.nanargmin(np.where(cnt[cs] > 0, dmean[cs], np.inf), 1),
    'worst': np.nanargmax(np.where(cnt[cs] > 0, dmean[cs], -np.inf), 1),
}
# z-score: per-submap mean/std of log-std
mu = np.array([L[S == k].mean() for k in range(ns)]); sd = np.array([L[S == k].std() for k in range(ns)])
rules['log-std z-score in own submap'] = np.nanargmin((lmed[cs] - mu) / sd + inf, 1)
# combined: normalised camera distance + percentile
cn = cmed[cs] / np.nanmedian(cmed[cs])
rules['percentile + camera rank'] = np.nanargmin(qmed[cs] + 0.5 * cn + inf, 1)
for name, ch in rules.items():
    print(f'{name:36s} {score(ch):.4f} m')
k = cnt[cs]
print(f"{'keep every submap (no rule)':36s} {float((np.nan_to_num(dmean[cs]) * k).sum() / k.sum()):.4f} m")
for a in [0.5, 1.0, 2.0, 4.0]:
    ch = np.nanargmin(lmed[cs] + a * np.log(cmed[cs]) + inf, 1)
    print(f"raw log-std + {a} ln(camera distance)   {score(ch):.4f} m")
# agreement between rules
print('uncertainty picks the oracle in', float((rules['raw log-std (current)'] == rules['oracle (best)']).mean()))
print('camera picks the oracle in', float((rules['nearest training camera'] == rules['oracle (best)']).mean()))
