"""Follow a scene's tracks live: print, per frame, which cameras see each track id, and
when a track appears or is lost. Resubscribes by itself if the server restarts.

    python follow_tracks.py --server 127.0.0.1:8080 --scene demo --frames 100
"""

from __future__ import annotations

import argparse

import crossview_client as cv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="127.0.0.1:8080")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--transport", choices=["grpc", "http"], default="grpc")
    ap.add_argument("--api-key")
    ap.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: never)")
    args = ap.parse_args()

    with cv.connect(args.server, args.transport, api_key=args.api_key) as client:
        client.wait_ready(timeout=60)
        live: set[int] = set()
        with client.subscribe(args.scene) as results:
            print(f"subscribed to {args.scene}", flush=True)
            for n, r in enumerate(results, start=1):
                now = {i.track_id for i in r.identities if i.track_id is not None}
                for t in sorted(now - live):
                    print(f"  track {t} appears")
                for t in sorted(live - now):
                    print(f"  track {t} not seen")
                live = now
                state = "complete" if r.complete else f"partial (missing {', '.join(r.missing_cameras)})"
                print(f"frame {r.frame_id} {state}, {r.status.value}, model {r.model_version}:", flush=True)
                for i in sorted(r.identities, key=lambda i: i.track_id or 0):
                    cams = ", ".join(m.camera for m in i.members)
                    print(f"  track {i.track_id}  confidence {i.confidence:.2f}  seen by {cams}", flush=True)
                if args.frames and n >= args.frames:
                    break


if __name__ == "__main__":
    main()
