#!/usr/bin/env python3
"""Alternating A/B timing (usage: ab_render.py ROUNDS "CMD_A" "CMD_B", each a `trove render ...`
command without --stats) of `trove render`: ROUNDS rounds, each runs A then B (order
swapped every other round). Per run: seconds.total from --stats (wall) and the process's
user+system CPU seconds. Prints medians and the medians of per-round ratios B/A."""
import json, subprocess, sys, statistics, os, tempfile, resource
rounds = int(sys.argv[1]); a_cmd = sys.argv[2]; b_cmd = sys.argv[3]
def run(cmd):
    stats = tempfile.mktemp(suffix='.json')
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd.split() + ['--stats', stats], check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    s = json.load(open(stats)); os.unlink(stats)
    return s['seconds']['total'], cpu, s.get('simd')
wall, cpu = {'A': [], 'B': []}, {'A': [], 'B': []}
rw, rc = [], []
for r in range(rounds):
    order = ['A', 'B'] if r % 2 == 0 else ['B', 'A']
    res = {}
    for k in order:
        res[k] = run(a_cmd if k == 'A' else b_cmd)
    for k in 'AB':
        wall[k].append(res[k][0]); cpu[k].append(res[k][1])
    rw.append(res['B'][0] / res['A'][0]); rc.append(res['B'][1] / res['A'][1])
    simd = res['A'][2]
m = statistics.median
print(f"wall: A {m(wall['A']):.3f} s, B {m(wall['B']):.3f} s, median B/A {m(rw):.3f} [{min(rw):.2f}, {max(rw):.2f}]; "
      f"cpu: A {m(cpu['A']):.3f} s, B {m(cpu['B']):.3f} s, median B/A {m(rc):.3f} [{min(rc):.2f}, {max(rc):.2f}]; simd {simd}")
