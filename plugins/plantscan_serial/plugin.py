"""Registers the ``grbl`` axis and the ``plantscan grbl-status`` command."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_serial.grbl import GrblAxis


@hookimpl
def plantscan_register_stages(registry):
    registry.add(GrblAxis)


@hookimpl
def plantscan_add_commands(subparsers):
    p = subparsers.add_parser(
        "grbl-status", help="state, position and settings of a GRBL controller")
    p.add_argument("port", help="device path or pyserial URL (socket://host:port)")
    p.add_argument("--baudrate", type=int, default=115200)

    def run(args) -> int:
        from plantscan_serial.grbl import print_status

        return print_status(args.port, args.baudrate)

    p.set_defaults(func=run)
