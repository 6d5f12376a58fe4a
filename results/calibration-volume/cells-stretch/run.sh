#!/bin/bash
# issue 18: the cells check's step taken along its line (stretch) against one Gauss-Newton step;
# the whole prototype from HDR stacks, fitted from the truth at the default --reliable 10 (as stall/from-truth-reliable-10)
cd /work/exp/cal
for v in base new; do
  mkdir -p $v
  /usr/bin/time -v ./prism-$v calibrate --merged merged --scene camera-as-built.json --max-steps 8 \
    --out $v/fitted.json --csv $v/fitted-params.csv > $v/calibrate.log 2> $v/time.log
done
echo done > run.done
