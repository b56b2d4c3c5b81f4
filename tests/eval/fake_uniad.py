"""A stand-in for an external UniAD evaluation process (tests only): it prints what UniAD's ``tools/test.py``
prints at the end of an evaluation (the nuScenes devkit's summary and per-class table, then the planning table),
or crashes, or hangs, as its first argument asks. It is not UniAD and computes nothing."""
import sys
import time

mode = sys.argv[1] if len(sys.argv) > 1 else "ok"
print("loading checkpoint from", sys.argv[2] if len(sys.argv) > 2 else "-", flush=True)
if mode == "hang":
    print("evaluating ...", flush=True)
    time.sleep(3600)
if mode == "crash":
    print("RuntimeError: CUDA out of memory.", file=sys.stderr, flush=True)
    sys.exit(3)
print("""mAP: 0.3823
mATE: 0.6841
mASE: 0.2796
mAOE: 0.4397
mAVE: 0.3925
mAAE: 0.1952
NDS: 0.4976
Eval time: 95.2s

Per-class results:
Object Class	AP	ATE	ASE	AOE	AVE	AAE
car	0.573	0.479	0.150	0.087	0.383	0.190
pedestrian	0.476	0.664	0.293	0.512	0.469	0.216
traffic_cone	0.601	0.453	0.332	nan	nan	nan

+---------------------------------------------------------------------+
|               uniad's definition planning metrics                   |
+-------------+--------+--------+--------+--------+--------+--------+
|   metrics   |  0.5s  |  1.0s  |  1.5s  |  2.0s  |  2.5s  |  3.0s  |
+-------------+--------+--------+--------+--------+--------+--------+
|   obj_col   | 0.0000 | 0.0005 | 0.0010 | 0.0020 | 0.0030 | 0.0041 |
| obj_box_col | 0.0002 | 0.0010 | 0.0022 | 0.0036 | 0.0051 | 0.0068 |
|      L2     | 0.2021 | 0.4512 | 0.7434 | 1.0731 | 1.4317 | 1.8131 |
+-------------+--------+--------+--------+--------+--------+--------+""", flush=True)
