"""``jamnav scenario show``, ``sinr`` and ``map``: a scenario and the SINR its radio world gives,
read without flying (the true model, or the levels a SINR-map network predicts)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from jamnav.arguments import (
    UsageError,
    add_jammer,
    add_scenario,
    check_range,
    comma_numbers,
    output_path,
    scenario_argument,
    scenario_with_jammer,
    sinr_map_argument,
)
from shared.radio import RadioModel


def _read_points(args: argparse.Namespace) -> np.ndarray:
    if args.at:
        return np.array([comma_numbers(text, 2, "--at") for text in args.at])
    source = args.points_json
    try:
        text = sys.stdin.read() if source == "-" else Path(source).read_text(encoding="utf-8")
        data = json.loads(text)
    except OSError as exc:
        raise UsageError(f"--points-json {source}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"--points-json {source}: not valid JSON ({exc.msg})") from None
    except UnicodeDecodeError:
        raise UsageError(f"--points-json {source}: not UTF-8 text") from None
    points = []
    for item in data if isinstance(data, list) else [None]:
        if isinstance(item, dict) and {"x", "y"} <= item.keys():
            item = [item["x"], item["y"]]
        if (
            not isinstance(item, list | tuple)
            or len(item) != 2
            # JSON true and false arrive as bool, a subclass of int
            or not all(isinstance(v, int | float) and not isinstance(v, bool)
                       and math.isfinite(v) for v in item)
        ):
            raise UsageError(
                f"--points-json {source}: expected a list of [x, y] or {{\"x\", \"y\"}} "
                "with finite numbers"
            )
        points.append([float(item[0]), float(item[1])])
    return np.array(points, dtype=np.float64).reshape(-1, 2)


def cmd_scenario_show(args: argparse.Namespace) -> int:
    scenario = scenario_argument(args)
    data = scenario.model_dump(mode="json")
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for section, values in data.items():
        if not isinstance(values, dict):
            print(f"{section} = {values}")
            continue
        print(f"[{section}]")
        for key, value in values.items():
            print(f"  {key} = {value}")
    return 0


def cmd_sinr(args: argparse.Namespace) -> int:
    if args.model:
        return _sinr_from_model(args)
    scenario = scenario_with_jammer(args)
    points = _read_points(args)
    radio = RadioModel(scenario)
    reading = radio.evaluate(points, radio.default_jammers)
    rows = [
        {
            "x": float(x),
            "y": float(y),
            "sinr_db": round(float(db), 6),
            "level": int(level),
            "serving_gbs": int(serving),
        }
        for (x, y), db, level, serving in zip(
            points, reading.sinr_db, reading.level, reading.serving_gbs, strict=True
        )
    ]
    print(json.dumps(rows))
    return 0


def _sinr_from_model(args: argparse.Namespace) -> int:
    """Levels predicted by a SINR-map network, in the shape of the true-map query; the
    network predicts levels only, so sinr_db and serving_gbs are null."""
    from planning.measuring import scenario_features
    from planning.networks import predict_levels

    if args.jammer or args.no_jammer:
        raise UsageError("--model: the network is the map of the jammer it was trained for; "
                         "--jammer/--no-jammer do not apply")
    scenario = scenario_argument(args)
    network, _ = sinr_map_argument("--model", args.model, scenario)
    points = _read_points(args)
    levels = predict_levels(network, scenario_features(scenario, points))
    rows = [
        {"x": float(x), "y": float(y), "sinr_db": None, "level": int(level), "serving_gbs": None}
        for (x, y), level in zip(points, levels, strict=True)
    ]
    print(json.dumps(rows))
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    from shared.plots import save_coverage_map

    scenario = scenario_with_jammer(args)
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise UsageError(f"--out {args.out}: the map is written as PNG; name it *.png")
    output_path("--out", args.out)
    check_range("--resolution", args.resolution, 20, 2000)
    share = save_coverage_map(scenario, RadioModel.jammers_of(scenario), out, args.resolution)
    print(f"wrote {out} (covered {share:.1%} of the area)", file=sys.stderr)
    return 0


# -- parsers ------------------------------------------------------------------------------------
def add_scenario_command(commands) -> None:
    scenario = commands.add_parser("scenario", help="inspect scenario files")
    scenario_commands = scenario.add_subparsers(dest="scenario_command", required=True)
    show = scenario_commands.add_parser("show", help="print the effective scenario")
    add_scenario(show)
    show.add_argument("--json", action="store_true", help="print JSON")
    show.set_defaults(handler=cmd_scenario_show)


def add_sinr_command(commands) -> None:
    sinr = commands.add_parser("sinr", help="SINR, level and serving GBS at points")
    add_scenario(sinr)
    add_jammer(sinr)
    where = sinr.add_mutually_exclusive_group(required=True)
    where.add_argument("--at", nargs="+", metavar="X,Y", help="points as X,Y")
    where.add_argument(
        "--points-json", metavar="FILE|-", help='JSON list of [x, y] or {"x", "y"}; - = stdin'
    )
    sinr.add_argument(
        "--model", metavar="PATH",
        help="predict levels with a SINR-map network (safetensors + JSON card) instead",
    )
    sinr.set_defaults(handler=cmd_sinr)


def add_map_command(commands) -> None:
    coverage = commands.add_parser("map", help="coverage map as in the paper's Fig. 3")
    add_scenario(coverage)
    add_jammer(coverage)
    coverage.add_argument("--out", required=True, metavar="FILE.png", help="the figure (PNG)")
    coverage.add_argument("--resolution", type=int, default=301,
                          help="grid points per side, 20 to 2000 (default 301)")
    coverage.set_defaults(handler=cmd_map)
