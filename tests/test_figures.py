"""pipeline/report/figures.py: every figure fits a rendered Markdown page with readable text, legends outside
the data, and each panel carries information (synthetic inputs, no files)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.image import AxesImage
from matplotlib.text import Text

from pipeline.evaluation.sequences import Trace
from pipeline.guidance.law import RendezvousResult
from pipeline.report import figures as F

RNG = np.random.default_rng(0)


def _run(
    z_end: float, lateral: float = 0.0, attack: tuple[int, int] | None = None, n: int = 40, flags: bool = False
) -> RendezvousResult:
    """A straight approach 60 m -> z_end over n steps, drifting `lateral` m sideways, attacked on steps [a, b)."""
    z = np.linspace(60, z_end, n + 1)
    pos = np.stack([np.linspace(0, lateral, n + 1), np.zeros(n + 1), z], 1)
    attacked = np.zeros(n, bool)
    if attack is not None:
        attacked[attack[0] : attack[1]] = True
    est = pos[:-1] + RNG.normal(0, 0.1, (n, 3)) + 5.0 * attacked[:, None]
    return RendezvousResult(
        pos,
        est,
        attacked,
        "docked",
        abs(z_end - 10),
        attack[0] if attack else None,
        attacked.copy() if flags else None,
        None,
    )


def _figures() -> dict[str, object]:
    base = _run(10)
    runs = [(60.0, 5, _run(10, attack=(0, 5))), (20.0, 15, _run(7, attack=(30, 40)))]
    rows = [
        {
            "attack": a,
            "eps": e,
            "detection_rate": 0.5,
            "harmful_undetected_rate": 0.2,
            "ci95_detection": [0.4, 0.6],
            "ci95_harmful_undetected": [0.1, 0.3],
        }
        for a in ("fgsm", "pgd")
        for e in (0.01, 0.1)
    ]
    trace = Trace(
        estimate_z=np.linspace(60, 10, 50),
        prob=RNG.random(50),
        flag=RNG.random(50) > 0.5,
        position_error=RNG.random(50),
        pose=np.zeros((50, 9)),
    )
    clean = RNG.integers(0, 256, (90, 160, 3), dtype=np.uint8)
    adv = {
        e: np.clip(clean + RNG.choice([-1, 1], clean.shape) * max(1, int(255 * e)), 0, 255).astype(np.uint8)
        for e in (0.5, 0.01, 0.1)
    }
    pred = {k: RNG.normal(size=9) for k in ["clean", *adv]}
    curve = (np.array([0, 0.01, 0.1, 1.0]), np.array([0, 0.5, 0.9, 1.0]))
    return {
        "pose_errors": F.pose_error_bars({"test": [{"range_m": ">60", "pos_mean_m": 0.5, "att_mean_deg": 3.0}]}),
        "error_vs_eps": F.error_vs_eps([0.01, 0.1], [1.0, 5.0], [3.0, 20.0], 0.3, 2.0),
        "shap_heatmaps": F.shap_heatmaps({"normal": RNG.random((9, 50)), "adversarial": RNG.random((9, 50))}),
        "roc": F.roc_curves({"LSTM": (*curve, 0.9), "MLP": (*curve, 0.9)}, highlight="LSTM"),
        "fgsm_example": F.attack_example(clean, adv, np.array([0.0, 0.0, 30.0]), pred, "fgsm"),
        "guidance_trajectories": F.guidance_trajectories(base, runs, 0.5, (0.0, 0.0, 10.0)),
        "guidance_defended": F.guidance_variants(
            [("undefended", runs[1][2]), ("hold", _run(10, 0.3, (30, 40), flags=True))],
            (0.0, 0.0, 10.0),
            "test cell",
            tolerance=1.0,
        ),
        "timeline": F.detection_timeline(np.linspace(60, 10, 50), np.arange(50) % 7 < 2, trace, 0.5, "T0"),
        "robustness": F.robustness_vs_eps(rows),
        "integrity": F.integrity_diagram(
            {
                name: {"bound": np.full(40, 11.0), "error": RNG.lognormal(0, 1, 40), "bound_is": "AL"}
                for name in ("clean", "burst at eps 0.05")
            },
            {"clean": RNG.random(60), "burst at eps 0.05": 5 * RNG.random(60)},
            np.full(60, 11.0),
            "test",
        ),
    }


@pytest.fixture(scope="module")
def figures():
    figs = _figures()
    for fig in figs.values():
        FigureCanvasAgg(fig).draw()
    return figs


def test_figures_fit_the_page_with_readable_text(figures):
    for name, fig in figures.items():
        assert fig.get_figwidth() <= F.WIDTH_IN + 1e-9, name
        texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
        small = {t.get_text() for t in texts if t.get_fontsize() < 8.5}
        assert not small, (name, small)
        for ax in fig.axes:
            if ax.axison and ax.has_data() and not ax.findobj(AxesImage) and ax.get_label() != "<colorbar>":
                shared = ax.get_shared_x_axes().get_siblings(ax)  # stacked panels: the bottom one names x
                assert any(a.get_xlabel() for a in shared) and ax.get_ylabel(), (name, ax.get_title())
        assert fig.get_suptitle() or name in ("shap_heatmaps", "timeline") or any(ax.get_title() for ax in fig.axes), (
            name
        )


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.mark.parametrize(
    "name", ["roc", "guidance_trajectories", "guidance_defended", "robustness", "timeline", "integrity"]
)
def test_legends_sit_outside_the_axes(figures, name):
    fig = figures[name]
    renderer = fig.canvas.get_renderer()
    assert fig.legends, name
    for legend in fig.legends:
        box = legend.get_window_extent(renderer)
        assert not any(_overlaps(box, ax.get_window_extent(renderer)) for ax in fig.axes), name


def test_roc_draws_the_highlighted_detector_last_and_distinct(figures):
    for ax in figures["roc"].axes:
        lines = {line.get_label(): line for line in ax.get_lines()}
        top = lines["LSTM (AUC 0.900)"]
        others = [line for label, line in lines.items() if line is not top]
        assert top.get_zorder() > max(line.get_zorder() for line in others)
        assert top.get_linewidth() > max(line.get_linewidth() for line in others)
    labels = [t.get_text() for t in figures["roc"].legends[0].get_texts()]
    assert not any("SPEC" in label for label in labels)


def test_attack_example_shows_the_original_once_and_stays_small(figures):
    fig = figures["fgsm_example"]
    images = [ax for ax in fig.axes if ax.findobj(AxesImage)]
    titles = [ax.get_title() for ax in images]
    assert len(images) == 1 + 3 + 1  # original, 3 eps, one perturbation
    assert sum("original" in t for t in titles) == 1
    assert [t.split("\n")[0] for t in titles[1:4]] == ["eps = 0.01", "eps = 0.1", "eps = 0.5"]
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110)
    assert len(buf.getvalue()) < 300_000


def test_guidance_panels_carry_information(figures):
    def spread(ax) -> float:
        ys = [np.asarray(line.get_ydata(), float) for line in ax.get_lines() if len(line.get_ydata()) > 1]
        return max(float(np.ptp(y)) for y in ys)

    on_axis = figures["guidance_trajectories"]
    assert len(on_axis.axes) == 2 and "approach axis" in on_axis.get_suptitle()  # x = y = 0: not drawn
    off_axis = F.guidance_trajectories(_run(10, 0.5), [(20.0, 5, _run(10, 0.8, (20, 25)))], 0.5, (0.0, 0.0, 10.0))
    assert len(off_axis.axes) == 3
    for fig in (on_axis, off_axis, figures["guidance_defended"]):
        for ax in fig.axes:
            assert spread(ax) > 0.1, ax.get_title()
    zoomed = figures["guidance_defended"].axes[1]  # distance to the target from 5 steps before the attack
    assert min(float(np.min(line.get_xdata())) for line in zoomed.get_lines() if len(line.get_xdata()) > 2) == 25


def test_pose_error_bars_leave_an_empty_range_bin_blank():
    """A range bin without frames (an imported set that never comes closer than 20 m) has only n = 0."""
    from pipeline.report.figures import pose_error_bars

    rows = [{"n": 0, "range_m": "60-45"}, {"n": 9, "range_m": "45-30", "pos_mean_m": 1.5, "att_mean_deg": 9.0}]
    fig = pose_error_bars({"train": rows, "test": rows})
    heights = [p.get_height() for p in fig.axes[0].patches]
    assert np.isnan(heights[0]) and heights[1] == 1.5
