"""reports/attack.md, the page of `rpod attack`: pose errors per eps on the stored and the float adversarial images."""

from __future__ import annotations

from typing import Any

from stages.config.sections import Attack


def attack_page(rows: list[dict[str, Any]], a: Attack, n: int) -> str:
    from pipeline.report.markdown import markdown_table

    table = markdown_table(
        [
            {
                "eps": r["eps"],
                "stored L-inf": r["stored_linf"],
                "pos. mean (m)": r["position_mean_m"],
                "pos. median (m)": r["position_median_m"],
                "att. mean (deg)": r["attitude_mean_deg"],
                "att. median (deg)": r["attitude_median_deg"],
            }
            for r in rows
        ],
        decimals=3,
    )
    float_table = markdown_table(
        [
            {
                "eps": r["eps"],
                "pos. mean, stored uint8 (m)": r["position_mean_m"],
                "pos. mean, float (m)": r["float_position_mean_m"],
                "att. mean, stored uint8 (deg)": r["attitude_mean_deg"],
                "att. mean, float (deg)": r["float_attitude_mean_deg"],
            }
            for r in rows[1:]
        ],
        decimals=3,
    )
    step = (
        ""
        if a.method == "fgsm"
        else (
            f" ({a.steps} steps, step size {a.step_size if a.step_size is not None else 'default'}"
            + (", random start" if a.method == "pgd" and a.random_start else "")
            + (f", momentum {a.momentum}" if a.method == "mifgsm" else "")
            + ")"
        )
    )
    return f"""# Adversarial attack on the pose estimator

Attack: **{a.method}**{step} on the **{a.loss}** loss (`full` = the training loss with its
learned weights), L-inf budget eps in pixel units ([0, 1] images), {n} test images (time: reports/metrics/attack.json).
FGSM is `x' = clip(x + eps * sign(grad_x L), 0, 1)`.

Errors are measured on the adversarial images **as stored** in `datasets/attack/adv.zarr` (uint8):
each pixel's perturbation is rounded to the nearest 8-bit level, but never to zero, so every
perturbed pixel keeps the sign of its perturbation. "stored L-inf" is the largest stored change of a
pixel: it can exceed eps by up to half a level (eps = 0.01 = 2.55 levels is stored as 3 levels).

{table}
Position error `||t_pred - t_gt||`, attitude error `2 acos(|<q_pred, q_gt>|)`.
{trend(rows)}

Same attack measured on the float adversarial images, before quantisation:

{float_table}
![the original, the stored adversarial image per eps and the amplified perturbation](figures/fgsm_example.png)
"""


def trend(rows: list[dict[str, Any]]) -> str:
    """One sentence on whether the mean errors grow with eps (rows[1:] in any eps order)."""
    by_eps = sorted(rows[1:], key=lambda r: float(r["eps"]))
    out = []
    for key, what in (("position_mean_m", "position"), ("attitude_mean_deg", "attitude")):
        vals = [rows[0][key]] + [r[key] for r in by_eps]
        grows = all(b >= a for a, b in zip(vals, vals[1:]))
        out.append(
            f"the mean {what} error {'grows' if grows else 'does not grow'} monotonically from clean "
            f"through eps = {', '.join(r['eps'] for r in by_eps)}"
        )
    return "Over this test set, " + "; ".join(out) + "."
