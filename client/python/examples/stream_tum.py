#!/usr/bin/env python3
"""Streams a TUM RGB-D folder into a lifemap map and prints what the server says per frame.

    python3 stream_tum.py 127.0.0.1:50051 ../shared/data/tum_fr1_xyz_subset office
        [--api-key-file KEY] [--ca ca.pem] [--groundtruth] [--out masks.npz]

Needs the lifemap package and Pillow (Debian python3-pil) for the PNGs.
"""
import argparse

import numpy as np

import lifemap
import lifemap.tum


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("target", help="lifemapd's host:port")
    parser.add_argument("folder", help="a TUM RGB-D folder (rgb.txt, depth.txt)")
    parser.add_argument("map", help="the map (created if absent)")
    parser.add_argument("--api-key-file", help="a file holding the API key")
    parser.add_argument("--ca", help="the server's CA (PEM): connect over TLS")
    parser.add_argument("--groundtruth", action="store_true",
                        help="send groundtruth.txt's poses (else the server tracks the camera)")
    parser.add_argument("--out", help="save every frame's entropy mask and labels here (.npz)")
    args = parser.parse_args()

    key = open(args.api_key_file).read().strip() if args.api_key_file else None
    with lifemap.Client(args.target, api_key=key, root_certificates=args.ca) as client:
        if args.map not in {m.name for m in client.maps()}:
            client.create_map(args.map)
        masks, labels = [], []
        frames = lifemap.tum.frames(args.folder, groundtruth=args.groundtruth)
        for result in client.stream(args.map, frames, robot="stream_tum.py"):
            if result.error is not None:
                print(f"frame {result.sequence}: rejected: {result.error}")
                continue
            line = f"frame {result.sequence}: {result.entropy_mask.mean():6.1%} masked"
            if result.labels is not None:
                present = np.unique(result.labels[result.labels != 255])
                line += ", labels " + " ".join(result.classes.get(c, str(c)) for c in present)
            if result.keyframe_id is not None:
                line += f", stored as keyframe {result.keyframe_id}"
            print(line)
            masks.append(result.entropy_mask)
            if result.labels is not None:
                labels.append(result.labels)
            visit = result.visit_id
        if masks:
            client.end_visit(visit)  # the recording is over: its visit ends
            print(f"visit {visit} ended")
        if args.out:
            np.savez_compressed(args.out, entropy_masks=np.array(masks),
                                labels=np.array(labels))
            print(f"saved {len(masks)} masks to {args.out}")


if __name__ == "__main__":
    main()
