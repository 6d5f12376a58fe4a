import sys, csv, numpy as np
sys.path.insert(0, '/work/main/build/python')
import prism
events, out = sys.argv[1], sys.argv[2]
truth = {e.id: e.vertices[0, :3] for e in prism.EventFile(events)}
est = {}
for row in csv.DictReader(open(out)):
    if row['vertex'] == '0': est[int(row['event'])] = np.array([float(row['x_mm']), float(row['y_mm']), float(row['depth_mm'])])
ids = sorted(truth)
err = np.array([np.linalg.norm(est[i] - truth[i]) if i in est else np.inf for i in ids])
depth = np.array([truth[i][2] for i in ids])
def line(m, name):
    e = err[m]
    print(f"{name:12s} n={m.sum():4d} mean={np.mean(e[np.isfinite(e)]):.3f} median={np.median(e):.3f} >3mm={int((e>3).sum())}")
line(np.ones(len(ids), bool), 'all')
line(depth < 20, 'depth<20')
line(depth >= 20, 'depth>=20')
