"""A calibration file whose reconstruction is this code's and whose optical simulator is another file's.

The image benchmarks (`image_pose_budget.py`, `image_contact_shape.py`, `yoto bench --via-images CAL`) render with a
calibration file's optical model and reconstruct with the same file's colour -> gradient model. When the calibration
code changes, recalibrating the presses refits both (the image model's round-trip gain depends on the gradient model),
so before / after figures would come from different images. This writes a file with the gradient model (and mask,
smoothing, ...) calibrated now from the presses, and the optical model (image model with its gain, noise level, blur)
of `--renderer`: the benchmark then renders the very same images and only the reconstruction differs. Prints the
calibration's summary.

    python benchmarks/recalibrate_keep_renderer.py --renderer CAL_GAIN.npz \\
        --background ../shared/data/gelsight_mini/background.png \\
        --presses ../shared/data/gelsight_mini/presses/6.310mm --ball-diameter-mm 6.31 --out CAL_NEW.npz
"""

from __future__ import annotations

import argparse
from dataclasses import replace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file whose optical model renders the images")
    parser.add_argument("--background", required=True)
    parser.add_argument("--presses", required=True)
    parser.add_argument("--ball-diameter-mm", type=float, required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    import numpy as np

    from yoto.errors import InputError
    from yoto.sensor.ball_calibration import calibrate
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.presses import list_press_images, load_image

    renderer = load_calibration(args.renderer)
    background = load_image(args.background)
    if not np.array_equal(background, renderer.background):
        raise InputError("the background is not the renderer's: its optical model adds to its own", args.background)
    presses = [load_image(path) for path in list_press_images(args.presses)]
    calibration, report = calibrate(background, presses, args.ball_diameter_mm * 1e-3)
    print(report.summary())
    mixed = replace(
        calibration,
        image_model=renderer.image_model,
        noise_std=renderer.noise_std,
        render_blur_px=renderer.render_blur_px,
    )
    mixed.save(args.out)
    print(f"wrote {args.out}: the gradient model calibrated now, the optical model of {args.renderer}")


if __name__ == "__main__":
    main()
