"""A dragged light through a running server: a point lamp moved in STEPS steps across a
scene, each relight asked for over REST with the iterative solver (warm from the step before,
as a user's drag is), and the server's own times printed per step (stats.ms, direct_ms,
solve_ms, iterations, products) with their medians over the steps after the first two.

    translux-server --bundles DIR --addr 127.0.0.1:18181 --backend cpu &
    python3 bench/scripts/drag.py http://127.0.0.1:18181/api/v1/scenes/ID/relight \
        [--steps 16] [--from 2.0 2.4 3.0] [--to 5.0 2.4 3.0] [--intensity 6 5.6 5]

The defaults walk across the furnished room of examples/scenes/furnished-room/ (metres).
Not a test: nothing here asserts a time.
"""
import argparse
import json
import statistics
import urllib.request


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("url")
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--from", dest="start", type=float, nargs=3, default=[2.0, 2.4, 3.0])
    ap.add_argument("--to", dest="end", type=float, nargs=3, default=[5.0, 2.4, 3.0])
    ap.add_argument("--intensity", type=float, nargs=3, default=[6.0, 5.6, 5.0])
    a = ap.parse_args()
    rows = []
    print("| step | ms | direct_ms | solve_ms | iterations | products | warm |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for k in range(a.steps):
        t = k / max(a.steps - 1, 1)
        pos = [p + t * (q - p) for p, q in zip(a.start, a.end)]
        body = {
            "lights": [{"type": "point", "position": pos, "intensity": a.intensity}],
            "solver": "iterative",
        }
        req = urllib.request.Request(
            a.url,
            data=json.dumps(body).encode(),
            headers={"Content-Type": "application/json", "Accept": "application/json"},
        )
        with urllib.request.urlopen(req, timeout=600) as r:
            s = json.load(r)["stats"]
        rows.append(s)
        print(f"| {k} | {s['ms']:.1f} | {s['direct_ms']:.1f} | {s['solve_ms']:.1f} | "
              f"{s['iterations']} | {s['products']} | {s['warm']} |", flush=True)
    tail = rows[2:] or rows
    med = {key: statistics.median(r[key] for r in tail) for key in ("ms", "direct_ms", "solve_ms")}
    print(f"\nmedian of steps 2..{a.steps - 1}: {med['ms']:.1f} ms ({1000 / med['ms']:.1f} fps): "
          f"direct {med['direct_ms']:.1f} ms, solve {med['solve_ms']:.1f} ms, "
          f"{statistics.median(r['iterations'] for r in tail)} iterations")


if __name__ == "__main__":
    main()
