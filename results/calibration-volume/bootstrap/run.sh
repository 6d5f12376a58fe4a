#!/bin/bash
# issue 18: bootstrap over the PSFs (the measurement behind `prism calibrate --bootstrap`, which does the same in one command). Each replicate draws 24 of the 24 HDR-merged PSFs with
# replacement (a PSF drawn twice counts twice) and refits from the full fit's end (base/, from the
# truth at --reliable 10) on the model's pixels, no cells check. The spread of the replicates'
# parameters is an uncertainty that does not lean on the Gauss-Newton matrix.
cd /work/exp/cal
R=${R:-12}
for r in $(seq 1 $R); do
  d=boot/r$r
  [ -f $d/done ] && continue
  rm -rf $d && mkdir -p $d/merged
  python3 - "$r" "$d/merged" <<'PY'
import random, sys, os
r, out = int(sys.argv[1]), sys.argv[2]
rng = random.Random(1000 + r)
src = sorted(f[:-5] for f in os.listdir('merged') if f.endswith('.json'))
pick = [rng.choice(src) for _ in src]
for i, p in enumerate(pick):
    for ext in ('.exr', '.json'):
        os.symlink(os.path.abspath(f'merged/{p}{ext}'), f'{out}/b{i:04d}{ext}')
open(f'{out}/../picks.txt', 'w').write('\n'.join(pick) + '\n')
PY
  ./prism-base calibrate --merged $d/merged --scene base/fitted.json --coarse-levels 0 --max-steps 6 \
    --cells-check 1 --out $d/fitted.json --csv $d/params.csv > $d/calibrate.log 2> $d/time.log && touch $d/done
done
echo done > boot/run.done
