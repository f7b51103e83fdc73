"""The ``jaxmm`` command line."""

import argparse
import sys


def _robot(args):
    from jaxmm.robots import load_ironcub, load_robot

    if args.urdf is None:
        robot = load_ironcub()
    else:
        robot = load_robot(args.urdf, joints=args.joints)
    print(robot.summary())


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxmm", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    robot = commands.add_parser("robot", help="print a robot summary (default: iRonCub)")
    robot.add_argument("--urdf", help="a URDF file (default: the assembled iRonCub)")
    robot.add_argument("--joints", nargs="+", help="optimised joints (default: all moving joints)")
    robot.set_defaults(run=_robot)
    args = parser.parse_args(argv)
    try:
        args.run(args)
    except (ValueError, KeyError, FileNotFoundError, TypeError) as error:
        print(f"jaxmm {args.command}: error: {error}", file=sys.stderr)
        return 2
    return 0
