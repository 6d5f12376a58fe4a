# Beyond-3-mm events of two reconstructions of the same events, paired:
# how many each alone has, and the exact McNemar test.
#   mcnemar.py EVENTS A.csv B.csv   (the prism module from the build: build/python)
import os, sys, csv
from math import comb
import numpy as np
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '../../build/python'))
import prism
truth = {e.id: e.vertices[0, :3] for e in prism.EventFile(sys.argv[1])}
def beyond_3mm(path):
    out = set()
    for r in csv.DictReader(open(path)):
        if r['vertex'] == '0':
            i = int(r['event'])
            if np.linalg.norm(np.array([float(r['x_mm']), float(r['y_mm']), float(r['depth_mm'])]) - truth[i]) > 3:
                out.add(i)
    return out
a, b = beyond_3mm(sys.argv[2]), beyond_3mm(sys.argv[3])
only_a, only_b = len(a - b), len(b - a)
n, k = only_a + only_b, min(only_a, only_b)
p = min(1.0, 2 * sum(comb(n, j) for j in range(k + 1)) / 2**n) if n else 1.0
print(f"A {len(a)}, B {len(b)} beyond 3 mm; A alone {only_a}, B alone {only_b}; exact McNemar p = {p:.3f}")
