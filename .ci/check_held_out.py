#!/usr/bin/env python3
"""Checks a training run's last validation against `nerfjit eval-views` of its checkpoint (issue 52).

    check_held_out.py NAME SUMMARY HELD_OUT --views N --min DB [--size W H] [--background R G B]
                      [--own | --pick I [I ...]] [--read-as TEXT]

SUMMARY is the run's summary JSON (its `validation` list), HELD_OUT what `eval-views --json` wrote for its
checkpoint. Prints both scores, then fails (exit 1) unless eval-views scored N views (of W×H pixels, on that
background, where given), the last validation reached DB, and the two agree within 0.1 dB (also inside the
masks where both have them). With `--cameras` on the run's own data (`--own`), eval-views' `held_out` means
are compared; with `--pick`, the mean over those views (issue 94). `--read-as` checks the words eval-views
used for how it read the views (`read as DTU`).
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
    parser.add_argument("--own", action="store_true", help="compare the means over the views training held out")
    parser.add_argument("--pick", type=int, nargs="+", metavar="I", help="compare the mean over these views")
    parser.add_argument("--read-as", help="words the protocol must hold about how the views were read")
    args = parser.parse_args()
    with open(args.summary) as file:
        val = json.load(file)["validation"][-1]
    with open(args.held_out) as file:
        again = json.load(file)
    scored = {"psnr": again["mean_psnr"], "masked_psnr": again.get("mean_masked_psnr")}
    failures = []
    if args.own:
        if again.get("held_out") is None:
            failures.append("eval-views did not read the views as the run's own data with views held out")
        else:
            held = again["held_out"]
            scored = {"psnr": held["mean_psnr"], "masked_psnr": held["mean_masked_psnr"]}
    if args.pick:
        views = [again["views"][i] for i in args.pick]
        masked = [v["masked_psnr"] for v in views if v.get("masked_psnr") is not None]
        scored = {
            "psnr": sum(v["psnr"] for v in views) / len(views),
            "masked_psnr": sum(masked) / len(masked) if masked else None,
        }
    print(f"{args.name}: val PSNR {val['val_psnr']:.2f} dB after {val['step']} steps; "
          f"eval-views {scored['psnr']:.2f} dB")
    if args.read_as and args.read_as not in again["protocol"]["views"]:
        failures.append(f"eval-views read {again['protocol']['views']}, not '{args.read_as}'")
    if len(again["views"]) != args.views:
        failures.append(f"eval-views scored {len(again['views'])} views, not {args.views}")
    if args.size and [again["width"], again["height"]] != args.size:
        failures.append(f"eval-views scored views of {again['width']}x{again['height']}, not {args.size}")
    if args.background and again["background"] != args.background:
        failures.append(f"eval-views used the background {again['background']}, not {args.background}")
    if val["val_psnr"] < args.min:
        failures.append(f"the run did not learn: {val['val_psnr']:.2f} dB is below {args.min}")
    if abs(val["val_psnr"] - scored["psnr"]) > 0.1:
        failures.append("eval-views does not score the checkpoint as its validation did")
    masked = (val.get("val_masked_psnr"), scored["masked_psnr"])
    if None not in masked and abs(masked[0] - masked[1]) > 0.1:
        failures.append("eval-views does not score the checkpoint inside the masks as its validation did")
    for failure in failures:
        print(f"{args.name}: {failure}", file=sys.stderr)
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
