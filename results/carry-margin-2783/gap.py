# The carry margin's measurement: for each event, how far above the coarse
# scan's best NLL lies the PSF that the exhaustive scan selects.
#   gap.py COARSE_DUMP EXHAUSTIVE_WINNERS [OUT.csv]
# COARSE_DUMP: one line per event, "E psf:nll psf:nll ..." sorted by NLL
# (PRISM_TMP_DUMP of measure-gap.diff, at the coarse level); EXHAUSTIVE_WINNERS:
# one PSF index per event (PRISM_TMP_WIN, with --level 2). Both runs see the
# same events in the same order (--serial-scans --threads 1: with more host
# threads the lines interleave). OUT.csv: per event the winner, its rank and
# gap at the coarse level, and how many PSFs lie within 30/40/50/60.
import sys
import numpy as np

dump_path, win_path = sys.argv[1], sys.argv[2]
events = []
for line in open(dump_path):
    if not line.startswith('E'):
        continue
    pairs = [p.split(':') for p in line.split()[1:]]
    events.append([(int(i), float(n)) for i, n in pairs])
winners = [int(l) for l in open(win_path) if l.strip()]
if len(events) != len(winners):
    sys.exit(f"{dump_path} has {len(events)} events, {win_path} {len(winners)}: not the same run's events")

gaps, ranks, missing, rows = [], [], 0, []
margins = (30, 40, 50, 60)
for e, (scored, win) in enumerate(zip(events, winners)):
    best = scored[0][1]
    rank = next((r for r, (i, _) in enumerate(scored) if i == win), None)
    if rank is None:  # beyond the dump's first 1500
        missing += 1
        continue
    gaps.append(scored[rank][1] - best)
    ranks.append(rank)
    rows.append([e, win, rank, f"{gaps[-1]:.3f}"] + [sum(1 for _, n in scored if n <= best + m) for m in margins])
gaps = np.array(gaps)
q = np.percentile(gaps, [50, 90, 95, 99, 100])
print(f"events {len(winners)}, winner beyond the dump's list: {missing}")
print("gap quantiles 50/90/95/99/max: " + " / ".join(f"{v:.1f}" for v in q))
print(f"winner's rank at the coarse level: max {max(ranks)}")
for margin in margins:
    carried = np.mean([sum(1 for _, n in s if n <= s[0][1] + margin) for s in events])
    print(f"margin {margin}: {int((gaps > margin).sum())} winners missed, {carried:.0f} PSFs within it on average (carried: clamped to 8..512)")
if len(sys.argv) > 3:
    with open(sys.argv[3], 'w') as f:
        f.write("event,winner_psf,coarse_rank,gap_nll," + ",".join(f"within_{m}" for m in margins) + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r) + "\n")
