"""Registers the ``gphoto2`` camera and the ``plantscan gphoto2-cameras`` command."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_gphoto.camera import GPhotoCamera


@hookimpl
def plantscan_register_stages(registry):
    registry.add(GPhotoCamera)


@hookimpl
def plantscan_add_commands(subparsers):
    p = subparsers.add_parser(
        "gphoto2-cameras",
        help="list the cameras libgphoto2 sees (model, port, serial) for a recipe")
    p.add_argument("--config", action="store_true",
                   help="also print every setting with its value and valid choices")

    def run(args) -> int:
        from plantscan_gphoto.camera import list_cameras

        return list_cameras(show_config=args.config)

    p.set_defaults(func=run)
