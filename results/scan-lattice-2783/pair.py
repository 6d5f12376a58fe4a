# Two reconstructions of the same events, paired: of the estimates that
# differ, which is closer to the truth and which has the lower NLL.
#   pair.py EVENTS A.csv B.csv   (the prism module from the build: build/python)
import os, sys, csv, numpy as np
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '../../build/python'))
import prism
truth = {e.id: e.vertices[0, :3] for e in prism.EventFile(sys.argv[1])}
def load(p):
    d={}
    for r in csv.DictReader(open(p)):
        if r['vertex']=='0': d[int(r['event'])]=(np.array([float(r['x_mm']),float(r['y_mm']),float(r['depth_mm'])]), float(r['nll']))
    return d
a,b=load(sys.argv[2]),load(sys.argv[3])
ids=[i for i in sorted(truth) if i in a and i in b]
ch=[i for i in ids if np.any(a[i][0]!=b[i][0])]
ea=np.array([np.linalg.norm(a[i][0]-truth[i]) for i in ch]); eb=np.array([np.linalg.norm(b[i][0]-truth[i]) for i in ch])
dn=np.array([a[i][1]-b[i][1] for i in ch])
print(f"changed {len(ch)}; err A-B mean {np.mean(ea-eb):+.3f} median {np.median(ea-eb):+.3f}; A better in {int((ea<eb).sum())}, B better in {int((eb<ea).sum())}")
print(f"NLL A-B: A lower in {int((dn<0).sum())}, B lower in {int((dn>0).sum())}, equal {int((dn==0).sum())}; median {np.median(dn):+.2f}, sum {dn.sum():+.1f}")
print("sign test of error: ", end=''); from math import comb
n=int((ea!=eb).sum()); k=int((ea<eb).sum()); p=sum(comb(n,j) for j in range(0,min(k,n-k)+1))*2/2**n; print(f"p={min(1,p):.3f}")
