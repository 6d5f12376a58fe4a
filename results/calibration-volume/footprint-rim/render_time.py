import prism, numpy as np, time, sys
res = []
for backend in ['vulkan', 'cpu']:
    for src in [(0, 0, 2), (5, 3, 6), (-7, 4, 15), (0, 0, 30)]:
        ts = []
        for k in range(3):
            t = time.time()
            prism.psf('prototype', src, derivatives=True, rays=1024, binning=16, splat='footprint', backend=backend)
            ts.append(time.time() - t)
        res.append(f'{backend} {src}: {np.median(ts):.3f} s')
print(sys.argv[1], ' | '.join(res))
