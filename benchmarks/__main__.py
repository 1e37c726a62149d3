"""`python -m benchmarks` (make bench): every benchmark, each printing its numbers and writing reports/bench/*.json.

The HaTT dataset build (about 10 minutes on 2 cores) runs only with --all; the service
benchmark runs one and two replicas; the deploy benchmark runs when nginx and redis-server are installed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks import (
    bandwidth,
    block_intake,
    features,
    foxglove_live,
    frame_post,
    hostile,
    hostile_chart,
    refusals,
    renderer,
    rosbag_read,
    service,
    uncertainty,
    visual,
    window_batch,
)


def main(argv: list[str]) -> int:
    # parsed first: a typo or --help must not start an hour of benchmarks that rewrite reports/bench
    args = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="Run every benchmark in turn (about an hour on 2 cores); each prints its numbers and writes "
        "reports/bench/*.json. One benchmark alone: python -m benchmarks.<name> --help.",
    )
    args.add_argument("--all", action="store_true", help="also build the HaTT–TexNet dataset (about 10 minutes more)")
    everything = args.parse_args(argv).all
    print("== tactile features: ours vs librosa ==", flush=True)
    features.main([])
    print("\n== visual embedding: torch vs onnxruntime ==", flush=True)
    visual.main([])
    print("\n== uncertainty per window: OOD check, interval ==", flush=True)
    uncertainty.main([])
    print("\n== selection per window: the hybrid's vibration fit against the perceptual rule ==", flush=True)
    if (Path("..") / "shared" / "data" / "hatt-texnet" / "models").is_dir():
        from benchmarks import selection

        selection.main([])
    else:
        print("(skipping benchmarks.selection: it reads HaTT's models from ../shared/data/hatt-texnet)", flush=True)
    print("\n== the real-time renderer: µs per second of output against lfilter ==", flush=True)
    renderer.main([])
    print("\n== the model-mediated link: bits per second to an operator's renderer ==", flush=True)
    bandwidth.main([])
    print("\n== the window pool: CPU per window by job size ==", flush=True)
    window_batch.main([])
    print("\n== the event loop: what a block costs before the window pool, against the bare parse ==", flush=True)
    block_intake.main([])
    print("\n== ROS 2 bags: a 10-minute bag read by RosbagSource against rosbags' bare read ==", flush=True)
    rosbag_read.main([])
    print("\n== a session followed live in Foxglove: events received, CPU it adds to the service ==", flush=True)
    foxglove_live.main([])
    print("\n== service: simulated robots on loopback ==", flush=True)
    service.main(["--replicas", "1", "2", "--profile"])
    print("\n== service: what a posted frame costs, against a /health GET ==", flush=True)
    frame_post.main([])
    print("\n== service: what a refused request costs ==", flush=True)
    refusals.main([])
    print("\n== service: the hostile-client probe's worst cases beside well-behaved robots ==", flush=True)
    hostile.main([])
    hostile_chart.main([str(hostile.DEFAULT_OUT)])
    from deploy.local import find_program

    if find_program("nginx") and find_program("redis-server"):
        from benchmarks import deploy

        print("\n== the deploy topology: nginx, two replicas, Redis ==", flush=True)
        deploy.main([])
    else:
        print("\n(skipping benchmarks.deploy: it needs nginx and redis-server)", flush=True)
    if everything:
        from benchmarks import dataset_build

        print("\n== building the HaTT–TexNet dataset ==", flush=True)
        dataset_build.main([])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
