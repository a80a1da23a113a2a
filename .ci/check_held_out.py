#!/usr/bin/env python3
"""Checks a training run's last validation against `nerfjit eval-views` of its checkpoint (issue 52).

    check_held_out.py NAME SUMMARY HELD_OUT --views N --min DB [--size W H] [--background R G B]

SUMMARY is the run's summary JSON (its `validation` list), HELD_OUT what `eval-views --json` wrote for its
checkpoint. Prints both scores, then fails (exit 1) unless eval-views scored N views (of W×H pixels, on that
background, where given), the last validation reached DB, and the two agree within 0.1 dB.
"""

import argparse
import json
import sys


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("name", help="the run's name in the messages")
    parser.add_argument("summary", help="the run's summary JSON")
    parser.add_argument("held_out", help="eval-views' JSON of the run's checkpoint")
    parser.add_argument("--views", type=int, required=True, help="the held-out views eval-views must score")
    parser.add_argument("--min", type=float, required=True, help="the least PSNR of the last validation, dB")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="the views' width and height")
    parser.add_argument("--background", type=float, nargs=3, metavar=("R", "G", "B"), help="their background")
    args = parser.parse_args()
    with open(args.summary) as file:
        val = json.load(file)["validation"][-1]
    with open(args.held_out) as file:
        again = json.load(file)
    print(f"{args.name}: val PSNR {val['val_psnr']:.2f} dB after {val['step']} steps; "
          f"eval-views {again['mean_psnr']:.2f} dB")
    failures = []
    if len(again["views"]) != args.views:
        failures.append(f"eval-views scored {len(again['views'])} views, not {args.views}")
    if args.size and [again["width"], again["height"]] != args.size:
        failures.append(f"eval-views scored views of {again['width']}x{again['height']}, not {args.size}")
    if args.background and again["background"] != args.background:
        failures.append(f"eval-views used the background {again['background']}, not {args.background}")
    if val["val_psnr"] < args.min:
        failures.append(f"the run did not learn: {val['val_psnr']:.2f} dB is below {args.min}")
    if abs(val["val_psnr"] - again["mean_psnr"]) > 0.1:
        failures.append("eval-views does not score the checkpoint as its validation did")
    for failure in failures:
        print(f"{args.name}: {failure}", file=sys.stderr)
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
