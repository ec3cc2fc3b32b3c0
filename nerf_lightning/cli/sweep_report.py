"""nerf-sweep-report <multirun dir>: report.md (every job's overrides and final PSNR) and psnr.png in that folder."""

from __future__ import annotations

import argparse

from nerf_lightning.outputs.sweeps import report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="nerf-sweep-report", description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir", help="a multirun folder, e.g. multirun/2026-11-21_10-00-00")
    args = parser.parse_args(argv)
    try:
        print(report(args.sweep_dir))
    except (FileNotFoundError, ValueError) as error:
        parser.exit(2, f"nerf-sweep-report: {error}\n")


if __name__ == "__main__":
    main()
