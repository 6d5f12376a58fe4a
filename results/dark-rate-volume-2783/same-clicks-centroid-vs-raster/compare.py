#!/usr/bin/env python3
"""The same clicks refined by the footprint before a122f0c (a large piece's light at its centroid) and after
(rasterised): per event 3D error, CRLB-free. Usage: compare.py DIR (run.sh's folder: positions.txt, old-N.csv, new-N.csv)."""
import csv, math, statistics, sys
d = sys.argv[1] if len(sys.argv) > 1 else '.'
rows = []
for line in open(f'{d}/positions.txt'):
    i, v = line.split()
    truth = [float(a) for a in v.split(',')]
    try:
        new = next(csv.DictReader(open(f'{d}/new-{i}.csv')))
        old = next(csv.DictReader(open(f'{d}/old-{i}.csv')))
    except (FileNotFoundError, StopIteration):
        continue
    err = lambda r: math.dist(truth, [float(r['x_mm']), float(r['y_mm']), float(r['depth_mm'])])
    rows.append((int(i), truth[2], err(old), err(new)))
print('event  depth_mm  centroid_err_mm  raster_err_mm')
for i, z, o, n in rows:
    print(f'{i:5d}  {z:8.1f}  {o:15.3f}  {n:13.3f}')
for name, sel in [('all', lambda z: True), ('depth < 10 mm', lambda z: z < 10), ('depth >= 10 mm', lambda z: z >= 10)]:
    r = [x for x in rows if sel(x[1])]
    if not r: continue
    o = [x[2] for x in r]; n = [x[3] for x in r]
    print(f'{name}: {len(r)} events; mean {statistics.mean(o):.3f} -> {statistics.mean(n):.3f} mm, median {statistics.median(o):.3f} -> '
          f'{statistics.median(n):.3f} mm, beyond 3 mm {sum(v > 3 for v in o)} -> {sum(v > 3 for v in n)}; '
          f'raster closer on {sum(b < a for _, _, a, b in r)}, farther on {sum(b > a for _, _, a, b in r)}')
