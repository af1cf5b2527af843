"""The table renderer (`yoto.sensor.table`) against real held-out ball presses, beside the fitted renderer.

Every press of the folder (`--data`: `background.png` and `presses/catalog.csv`, as ../shared/data/gelsight_mini) is
held out once (`--folds` folds by press index, as `yoto sensor validate` folds them): the table is read off the other
folds' presses, and `yoto sensor calibrate` on those presses gives the fitted renderer (`optical.render_image`, the
inverse of our calibration's model with its round-trip gain). Each held-out press's Hertz height map at its contact
circle (found by a calibration on all presses) is rendered noise-free by both and compared with the real image
(colour change against the background, the press's lighting drift removed): the RMS per channel (R, G, B levels)
inside the contact (r < a), on its rim (a <= r < 1.5 a) and over both, median over the held-out presses; and what our
reconstruction reads on each rendered press (with noise), as `yoto sensor validate` reads a real one: the fold's
calibration, a sphere fitted inside the found circle, its radius against the ball's (median and median |error| over
the held-out presses; the real presses' own line comes first), and the median CPU time of one noise-free render. It
prints one line per table setting (`--blurs`, `--steps`, `--places`, `--pressed-depths-mm`, `--per-pixel-gains`) and
one for the fitted renderer, and the real frames' noise level against which the RMS stands (the rendered images it
compares carry none).

    python benchmarks/table_renderer_check.py --data ../shared/data/gelsight_mini --places 4 5 6 --per-pixel-gains 1

(the defaults: the table's own settings, with and without the per-pixel gain).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

GAINS = {1: "per-pixel gain", 0: "no gain"}


def press_errors(rendered: np.ndarray, real_change: np.ndarray, background: np.ndarray, r: np.ndarray, a: float):
    """RMS per channel of the rendered colour change against the real one: inside, rim, both ((3,) each)."""
    change = rendered.astype(np.float32) - background.astype(np.float32)
    error = change - real_change
    regions = (r < a, (r >= a) & (r < 1.5 * a), r < 1.5 * a)
    return [np.sqrt(np.mean(error[region] ** 2, axis=0)) for region in regions]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/gelsight_mini")
    parser.add_argument("--folds", type=int, default=4)
    parser.add_argument("--blurs", type=float, nargs="+", default=[2.0])
    parser.add_argument("--steps", type=float, nargs="+", default=[0.05])
    parser.add_argument("--places", type=int, nargs="+", default=[5])
    parser.add_argument(
        "--pressed-depths-mm", type=float, nargs="+", default=[0.8], help="depths the zero-gradient change fades in by"
    )
    parser.add_argument(
        "--per-pixel-gains",
        type=int,
        nargs="+",
        default=[1, 0],
        help="1: the change read relative to each pixel's "
        "background (the default); 0: as stop 16's table (the lighting averaged over each place)",
    )
    args = parser.parse_args()

    from yoto.sensor.ball_calibration import calibrate
    from yoto.sensor.optical import render_image
    from yoto.sensor.sphere import press_height_map
    from yoto.sensor.table import fit_table_sensor, read_press_folder
    from yoto.sensor.validation import evaluate_press

    def radius_error(image, calibration, index, fold) -> float:
        found, _ = evaluate_press(image, calibration, diameter_m / 2, str(index), fold)
        return found.radius_error(diameter_m / 2 * 1e3) if found.found else float("nan")

    background, images, diameter_m = read_press_folder(args.data)
    full, report = calibrate(background, images, diameter_m)
    spec = full.spec
    circles = [(p.contact_x_px, p.contact_y_px, p.contact_radius_px) for p in report.presses]
    shape = (spec.height_px, spec.width_px)
    ys, xs = np.mgrid[: shape[0], : shape[1]]
    real_changes, distances, heights = [], [], []
    for image, (cx, cy, a) in zip(images, circles, strict=True):
        r = np.hypot(xs - cx, ys - cy)
        change = image.astype(np.float32) - background.astype(np.float32)
        change -= np.median(change[r > 3 * a], axis=0)
        real_changes.append(change)
        distances.append(r)
        heights.append(press_height_map(cx, cy, a, diameter_m / 2, spec))
    noise = np.median(
        [np.std(c[r > 3 * a], axis=0) for c, r, (_, _, a) in zip(real_changes, distances, circles, strict=True)], axis=0
    )
    print(
        f"{len(images)} presses, {args.folds} folds; real frames' noise against the background (std per channel): "
        f"{np.round(noise, 2)}"
    )

    settings = [
        (step, places, blur, depth, gain)
        for step in args.steps
        for places in args.places
        for blur in args.blurs
        for depth in args.pressed_depths_mm
        for gain in args.per_pixel_gains
    ]
    errors: dict[str, list] = {
        f"table {s:.2f} bins, {p}x{p} places, blur {b:.1f} px, pressed {d:.2f} mm, {GAINS[g]}": []
        for s, p, b, d, g in settings
    }
    errors["fitted renderer (our calibration's inverse)"] = []
    radii: dict[str, list[float]] = {label: [] for label in errors}
    radii["real presses"] = []
    seconds: dict[str, list[float]] = {label: [] for label in errors}
    for fold in range(args.folds):
        train = [i for i in range(len(images)) if i % args.folds != fold]
        held = [i for i in range(len(images)) if i % args.folds == fold]
        calibration, _ = calibrate(background, [images[i] for i in train], diameter_m)
        for (step, places, blur, depth, gain), label in zip(settings, errors):
            sensor = fit_table_sensor(
                background,
                [images[i] for i in train],
                [circles[i] for i in train],
                diameter_m / 2,
                spec,
                step=step,
                places=places,
                blur_px=blur,
                pressed_depth_m=depth * 1e-3,
                per_pixel_gain=bool(gain),
            )
            for i in held:
                start = time.process_time()
                rendered = sensor.render(heights[i], None)
                seconds[label].append(time.process_time() - start)
                errors[label].append(press_errors(rendered, real_changes[i], background, distances[i], circles[i][2]))
                noisy = sensor.render(heights[i], np.random.default_rng(i))
                radii[label].append(radius_error(noisy, calibration, i, fold))
        fitted = "fitted renderer (our calibration's inverse)"
        for i in held:
            start = time.process_time()
            rendered = render_image(heights[i], calibration)
            seconds[fitted].append(time.process_time() - start)
            errors[fitted].append(press_errors(rendered, real_changes[i], background, distances[i], circles[i][2]))
            radii[fitted].append(
                radius_error(render_image(heights[i], calibration, np.random.default_rng(i)), calibration, i, fold)
            )
            radii["real presses"].append(radius_error(images[i], calibration, i, fold))
    real = np.array(radii["real presses"])
    print(
        f"real presses read by the fold's calibration: sphere radius median {np.nanmedian(real):+.1%}, median |error| "
        f"{np.nanmedian(np.abs(real)):.1%}"
    )
    print("RMS of the rendered colour change against the real, levels R/G/B, median over held-out presses:")
    for label, rows in errors.items():
        inside, rim, both = (np.median([row[k] for row in rows], axis=0) for k in range(3))

        def text(values: np.ndarray) -> str:
            return "/".join(f"{v:.1f}" for v in values)

        read = np.array(radii[label])
        print(
            f"  {label:>60}: inside {text(inside)}, rim {text(rim)}, both {text(both)} (mean {both.mean():.2f}); "
            f"sphere radius read {np.nanmedian(read):+.1%}, median |error| {np.nanmedian(np.abs(read)):.1%}; "
            f"render {1e3 * np.median(seconds[label]):.0f} ms CPU"
        )


if __name__ == "__main__":
    main()
