"""The QA report's pictures: arrays in, PNG bytes out (matplotlib, Agg, no window).

Every function draws one picture from numbers it is given, in millimetres and degrees, and returns
it as PNG bytes without a time stamp or software tag in them, so the same numbers give the same
bytes (fonts and the renderer are matplotlib's own). Nothing here reads files: the report stage
gathers the data (``flows.stages.qa_report``).
"""

from __future__ import annotations

import functools
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after the backend is chosen
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402
from matplotlib.path import Path  # noqa: E402

__all__ = ["png", "face_map", "intensity_image", "registration_graph", "mesh_view", "weld_section", "along_weld",
           "histogram", "sample_chart", "stress_along_toes", "stress_field", "ViewedFace", "AlongWeldSeries"]

_DPI = 100
_STYLE = {"font.size": 8, "axes.titlesize": 9, "axes.labelsize": 8, "legend.fontsize": 7, "svg.hashsalt": "weldrecon",
          "path.simplify": False}


def png(fig) -> bytes:
    """The figure as PNG bytes, closed; no time or software in the file: same drawing, same bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def _figure(width_in: float, height_in: float, margins: tuple[float, float, float, float] | None = None):
    """A figure laid out by matplotlib's constrained layout, or (``margins``: left, bottom, right,
    top in inches, for the many small pictures: quicker) with fixed margins."""
    with plt.rc_context(_STYLE):
        if margins is None:
            return plt.figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")
        fig = plt.figure(figsize=(width_in, height_in), dpi=_DPI)
        left, bottom, right, top = margins
        fig.subplots_adjust(left=left / width_in, bottom=bottom / height_in, right=1 - right / width_in,
                            top=1 - top / height_in)
        return fig


@dataclass(frozen=True)
class ViewedFace:
    """One face of the part seen from outside: ``values`` (rows, cols) on a grid of ``cell_mm``
    cells whose first cell's lower corner is ``origin_mm`` (x, y); NaN where nothing is drawn."""

    name: str
    values: np.ndarray
    origin_mm: tuple[float, float]
    cell_mm: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        rows, cols = self.values.shape
        x0, y0 = self.origin_mm
        return (x0, x0 + cols * self.cell_mm, y0, y0 + rows * self.cell_mm)


def face_map(faces: Sequence[ViewedFace], *, title: str, unit: str, cmap: str = "viridis", discrete: bool = False,
             vmax: float | None = None, paths: Sequence[Sequence[tuple[str, np.ndarray]]] | None = None,
             lines: Sequence[np.ndarray] = ()) -> bytes:
    """Each face's grid as a colour map, one panel per face, with one colour scale; ``paths`` (per
    face: (label, (k, 2) mm)) are drawn as arrows (the passes' sweeps), ``lines`` ((k, 2) mm) as
    dashed lines (the weld lines). ``discrete``: integer values (counts), one colour each."""
    finite = np.concatenate([f.values[np.isfinite(f.values)].ravel() for f in faces]) if faces else np.zeros(0)
    top = vmax if vmax is not None else (float(np.nanpercentile(finite, 99)) if len(finite) else 1.0)
    top = max(top, 1e-9)
    width = max(max(f.extent[1] - f.extent[0] for f in faces), 1.0) if faces else 1.0
    height = sum(max(f.extent[3] - f.extent[2], 1.0) for f in faces) if faces else 1.0
    fig_w = 7.5
    fig_h = min(max(1.0 + fig_w * 0.85 * height / width, 2.0), 9.0)
    fig = _figure(fig_w, fig_h)
    axes = fig.subplots(max(len(faces), 1), 1, squeeze=False)[:, 0]
    if discrete:
        n = int(max(round(top), 1))
        cmap_obj = plt.get_cmap(cmap, n)
        norm = matplotlib.colors.BoundaryNorm(np.arange(0.5, n + 1.5), n)
    else:
        cmap_obj = plt.get_cmap(cmap)
        norm = matplotlib.colors.Normalize(0.0, top)
    image = None
    for k, (ax, face) in enumerate(zip(axes, faces)):
        image = ax.imshow(face.values, origin="lower", extent=face.extent, cmap=cmap_obj, norm=norm,
                          interpolation="nearest")
        ax.set_title(face.name, loc="left")
        ax.set_aspect("equal")
        ax.set_xlabel("x, mm")
        ax.set_ylabel("y, mm")
        for line in lines:
            ax.plot(line[:, 0], line[:, 1], "--", color="white", lw=0.8)
        x0, x1, y0, y1 = face.extent
        for label, xy in (paths[k] if paths and k < len(paths) else ()):
            start, end = np.clip(xy[0], (x0, y0), (x1, y1)), np.clip(xy[-1], (x0, y0), (x1, y1))
            ax.annotate("", xy=end, xytext=start, arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 0.7})
            ax.text(*((start + end) / 2), label, fontsize=5, color="tab:red", ha="center", va="center",
                    bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
    if image is not None:
        bar = fig.colorbar(image, ax=list(axes), shrink=0.8)
        bar.set_label(unit)
        if discrete:
            bar.set_ticks(np.arange(1, n + 1, max(1, n // 10)))
    fig.suptitle(title, x=0.02, ha="left")
    return png(fig)


def intensity_image(image: np.ndarray, *, extent_mm: tuple[float, float, float, float], title: str,
                    stickers_mm: np.ndarray, radius_mm: float) -> bytes:
    """A pass's backscatter image (``image`` rows: profiles, columns: along the laser line) drawn
    with the sweep across and the laser line up, in mm (``extent_mm``: line from, to, sweep from,
    to), each detected sticker circled (``stickers_mm``: (k, 2) (along the line, along the sweep)).
    The two axes are scaled apart (a pass is far longer than wide): circles show as the image does."""
    fig = _figure(5.6, 1.9, margins=(0.5, 0.45, 0.1, 0.25))
    ax = fig.add_subplot()
    shown = np.where(image > 0, image, np.nan).astype(np.float32).T
    x0, x1, y0, y1 = extent_mm
    ax.imshow(shown, origin="lower", extent=(y0, y1, x0, x1), cmap="gray", aspect="auto", interpolation="nearest",
              vmin=0, vmax=float(np.nanpercentile(shown, 99.5)) if np.isfinite(shown).any() else 1.0)
    _add_circles(ax, [Ellipse((y, x), 2 * radius_mm, 2 * radius_mm, fill=False, color="tab:red", lw=0.8)
                      for x, y in np.asarray(stickers_mm, np.float64).reshape(-1, 2)])
    ax.set_title(title, loc="left")
    ax.set_xlabel("along the sweep, mm")
    ax.set_ylabel("along the line, mm")
    ax.set_facecolor("#203040")
    return png(fig)


@functools.cache
def _unit_circle_extrema() -> np.ndarray:
    """The start, end and axis-aligned extrema of each Bezier segment of the unit circle's path
    (an Ellipse's), as ``Axes._update_patch_limits`` finds them."""
    vertices = []
    for curve, _ in Path.unit_circle().iter_bezier(simplify=False):
        _, dzeros = curve.axis_aligned_extrema()
        vertices.append(curve([0, *dzeros, 1]))
    return np.vstack(vertices)


def _add_circles(ax, circles: Sequence[Ellipse]) -> None:
    """``ax.add_patch`` of each circle, with the data limits it would give them (the unit circle's
    extrema, placed) updated once for all: the same limits, drawn the same, without add_patch
    finding the unit circle's extrema again for every circle (it was 40 % of a pass's picture)."""
    if not circles:
        return
    for circle in circles:
        ax.add_artist(circle)
    ax.update_datalim(np.concatenate([(circle.get_transform() - ax.transData).transform(_unit_circle_extrema())
                                      for circle in circles]))


def registration_graph(names: Sequence[str], groups: Sequence[str], edges: Sequence[tuple[int, int, int, float]],
                       surface_edges: Sequence[tuple[int, int, float]] = (), *, title: str) -> bytes:
    """The passes on a circle (grouped by setup, in scan order) and the pass pairs that registered
    them: ``edges`` (a, b, target pairs, median residual mm) coloured by residual (um), wider for
    more targets; ``surface_edges`` (a, b, RMS mm), the overlapping surfaces the refinement used,
    thin and grey."""
    n = len(names)
    angle = np.pi / 2 - 2 * np.pi * np.arange(n) / max(n, 1)
    xy = np.c_[np.cos(angle), np.sin(angle)]
    fig = _figure(7.5, 6.2)
    ax = fig.add_subplot()
    if surface_edges:
        ax.add_collection(LineCollection([xy[[a, b]] for a, b, _ in surface_edges], colors="0.75", linewidths=0.5,
                                         zorder=1))
    image = None
    if edges:
        residual_um = np.array([e[3] * 1000 for e in edges])
        top = max(float(np.nanmax(residual_um)) if np.isfinite(residual_um).any() else 1.0, 1.0)
        widths = [0.6 + 1.2 * math.log10(max(e[2], 1)) for e in edges]
        collection = LineCollection([xy[[e[0], e[1]]] for e in edges], array=residual_um, cmap="plasma",
                                    norm=matplotlib.colors.Normalize(0, top), linewidths=widths, zorder=2)
        image = ax.add_collection(collection)
        bar = fig.colorbar(image, ax=ax, shrink=0.7)
        bar.set_label("median target residual of the pair, um")
    palette = plt.get_cmap("tab10")
    setups = list(dict.fromkeys(groups))
    for k, (name, group) in enumerate(zip(names, groups)):
        colour = palette(setups.index(group) % 10)
        ax.plot(*xy[k], "o", ms=5, color=colour, zorder=3)
        right = xy[k][0] >= -1e-9
        ax.text(*(xy[k] * 1.06), name, fontsize=6, rotation=math.degrees(angle[k]) + (0 if right else 180),
                rotation_mode="anchor", ha="left" if right else "right", va="center", color=colour)
    for j, setup in enumerate(setups):
        ax.plot([], [], "o", color=palette(j % 10), label=f"setup {setup}")
    if surface_edges:
        ax.plot([], [], color="0.75", label="overlap used by the refinement")
    ax.legend(loc="lower left", bbox_to_anchor=(0, -0.02), frameon=False)
    ax.set_xlim(-1.3, 1.3)
    ax.set_ylim(-1.3, 1.3)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, loc="left")
    return png(fig)


def _rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """World -> view: x right, y up, z toward the viewer, who looks from ``azimuth`` (about z, from
    +x) and ``elevation`` (above the x-y plane)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    toward = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    right = np.cross([0.0, 0.0, 1.0], toward)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-9 else np.array([0.0, 1.0, 0.0])
    up = np.cross(toward, right)
    return np.array([right, up, toward])


def mesh_view(vertices: np.ndarray, triangles: np.ndarray, *, azimuth_deg: float, elevation_deg: float, title: str,
              highlight: np.ndarray | None = None, width_in: float = 7.5, height_in: float = 3.6) -> bytes:
    """The mesh seen from a direction, orthographic, Lambert-shaded faces drawn back to front;
    ``highlight`` (t,) bool: faces drawn in another colour (the weld zone). Back faces are culled,
    so an open mesh shows its inside as missing."""
    R = _rotation(azimuth_deg, elevation_deg)
    v = np.asarray(vertices, np.float64) @ R.T
    tri = np.asarray(triangles, np.int64)
    corners = v[tri]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normal, axis=1)
    front = (normal[:, 2] > 0) & (length > 0)
    light = np.array([-0.25, 0.3, 0.92])  # from over the viewer's left shoulder
    light /= np.linalg.norm(light)
    shade = np.clip((normal[front] / length[front, None]) @ light, 0, 1) * 0.7 + 0.3
    base = np.where((highlight[front] if highlight is not None else np.zeros(front.sum(), bool))[:, None],
                    np.array([[0.85, 0.45, 0.15]]), np.array([[0.62, 0.68, 0.78]]))
    colours = np.c_[base * shade[:, None], np.ones(front.sum())]
    depth = corners[front, :, 2].mean(axis=1)
    order = np.argsort(depth, kind="stable")
    polys = corners[front][order][:, :, :2]
    fig = _figure(width_in, height_in)
    ax = fig.add_subplot()
    ax.add_collection(PolyCollection(polys, facecolors=colours[order], edgecolors=colours[order], linewidths=0.15,
                                     antialiased=False))
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    pad = 0.03 * float(max(hi - lo))
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, loc="left")
    return png(fig)


def weld_section(u: np.ndarray, h: np.ndarray, *, title: str, toes: Sequence[tuple[float, str]],
                 nominal: Sequence[tuple[np.ndarray, np.ndarray, str]], failing: bool, half_span_mm: float,
                 toe_points: Sequence[tuple[float, float, str]] = ()) -> bytes:
    """One section across the weld: the measured points (``u`` across, ``h`` up from the plate at
    the weld's centre, mm, true scale, ``half_span_mm`` either side of the centre), the nominal
    geometry (``nominal``: (u, h, label) lines), each toe where it was measured (``toes``: (u, label)
    across; ``toe_points``: (u, h, label), a fillet weld's)."""
    fig = _figure(3.7, 2.0, margins=(0.6, 0.36, 0.08, 0.22))  # one of many: fixed margins, quicker
    ax = fig.add_subplot()
    shown = np.abs(u) <= half_span_mm
    u, h = u[shown], h[shown]
    for nu, nh, label in nominal:
        ax.plot(nu, nh, "--", color="0.45", lw=0.9, label=label)
    ax.plot(u, h, ".", ms=1.6, color="tab:blue", label="measured points")
    for position, label in toes:
        ax.axvline(position, color="tab:red" if failing else "tab:green", lw=0.7, ls=":")
        ax.text(position, 0.02, label, transform=ax.get_xaxis_transform(), fontsize=6, ha="center",
                color="tab:red" if failing else "tab:green")
    for tu, th, label in toe_points:
        ax.plot([tu], [th], "o", ms=4, mfc="none", color="tab:red" if failing else "tab:green")
        ax.annotate(label, (tu, th), xytext=(4, 4), textcoords="offset points", fontsize=6,
                    color="tab:red" if failing else "tab:green")
    ax.set_xlim(-half_span_mm, half_span_mm)
    if len(h):
        ax.set_ylim(float(np.min(h)) - 1.0, float(np.max(h)) + 1.5)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("across the weld, mm")
    ax.set_ylabel("height, mm")
    ax.set_title(title, loc="left", color="tab:red" if failing else "black")
    ax.legend(loc="upper right", frameon=False, fontsize=6)
    return png(fig)


def toe_closeups(closeups: Sequence, *, title: str) -> bytes:
    """One section's toes seen close (``tasks.weld_views.ToeCloseup``), a panel each: the measured
    points along the plate and over it up to 1 mm, the height exaggerated (the factor in each
    panel's corner: an HFMI groove of 0.3 mm or a toe's rounding cannot be seen at true scale),
    the fitted toe drawn over them."""
    panels = max(len(closeups), 1)
    left, bottom, right, top, gap = 0.45, 0.34, 0.08, 0.36, 0.5  # one of many: fixed margins (inches), quicker
    fig = _figure(3.7 * panels, 2.2, margins=(left, bottom, right, top))
    fig.subplots_adjust(wspace=gap / ((3.7 * panels - left - right - (panels - 1) * gap) / panels))
    for k, c in enumerate(closeups):
        ax = fig.add_subplot(1, len(closeups), k + 1)
        ax.plot(c.t_mm, c.n_mm, ".", ms=2.0, color="tab:blue", label="measured points")
        if len(c.model_t_mm):
            ax.plot(c.model_t_mm, c.model_n_mm, "-", color="tab:red", lw=0.9, label="the fitted toe")
        if len(c.t_mm):
            lo, hi = float(np.min(c.n_mm)), min(float(np.max(c.n_mm)), 1.0)  # the toe: up to 1 mm over its plate
            ax.set_ylim(lo - 0.05, hi + 0.05)
            ax.set_xlim(float(np.min(c.t_mm)), float(np.max(c.t_mm)))
            # how much taller than true scale the panel draws heights
            box = ax.get_position()
            w_in, h_in = box.width * fig.get_figwidth(), box.height * fig.get_figheight()
            factor = (np.ptp(ax.get_xlim()) / w_in) / (np.ptp(ax.get_ylim()) / h_in)
            ax.text(0.98, 0.95, f"height x{factor:.1f}", transform=ax.transAxes, ha="right", va="top", fontsize=6)
        ax.set_title(c.label, loc="left", fontsize=6)
        ax.set_xlabel("along the plate, out from the toe, mm", fontsize=6)
        ax.set_ylabel("over the plate, mm", fontsize=6)
        ax.tick_params(labelsize=6)
        ax.legend(loc="lower left", frameon=False, fontsize=5)
    fig.suptitle(title, x=0.01, ha="left", fontsize=7)
    return png(fig)


@dataclass(frozen=True)
class AlongWeldSeries:
    """One figure's values along the weld: ``position_mm`` and ``value`` (n,) per curve label,
    ``sigma`` (n,) its 1-sigma (NaN: none), the limits (None: not checked), failing (n,) bool."""

    figure: str
    unit: str
    curves: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    limit_min: float | None
    limit_max: float | None


def along_weld(series: Sequence[AlongWeldSeries], *, title: str, error_bars: bool = False) -> bytes:
    """The figures along the weld, one panel each, the 1-sigma as bands (or as error bars at each
    position: ``error_bars``), the acceptance limits drawn, failing sections marked."""
    n = max(len(series), 1)
    fig = _figure(7.5, 1.55 * n + 0.6)
    axes = fig.subplots(n, 1, squeeze=False, sharex=True)[:, 0]
    palette = plt.get_cmap("tab10")
    for ax, s in zip(axes, series):
        for k, (label, (pos, val, sig, bad)) in enumerate(s.curves.items()):
            colour = palette(k % 10)
            ax.plot(pos, val, "-", lw=0.8, color=colour, label=label)
            ok = np.isfinite(sig)
            if ok.any() and error_bars:
                ax.errorbar(pos[ok], val[ok], yerr=sig[ok], fmt="none", ecolor=colour, elinewidth=0.6, capsize=1.5)
            elif ok.any():
                ax.fill_between(pos, val - np.where(ok, sig, 0), val + np.where(ok, sig, 0), color=colour, alpha=0.2,
                                lw=0)
            if bad.any():
                ax.plot(pos[bad], val[bad], "x", color="tab:red", ms=4)
        for limit in (s.limit_min, s.limit_max):
            if limit is not None:
                ax.axhline(limit, color="tab:red", lw=0.8, ls="--")
        ax.set_ylabel(f"{s.figure}, {s.unit}")
        ax.legend(loc="upper right", ncols=4, frameon=False)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("position along the weld line, mm")
    fig.suptitle(title, x=0.02, ha="left")
    return png(fig)


def histogram(values: np.ndarray, *, bins: np.ndarray, title: str, xlabel: str,
              mark: float | None = None) -> bytes:
    """A histogram (log count), ``mark`` drawn as a dashed line (a bound)."""
    fig = _figure(3.7, 2.4)
    ax = fig.add_subplot()
    ax.hist(np.asarray(values, np.float64), bins=bins, color="tab:blue")
    ax.set_yscale("log")
    if mark is not None:
        ax.axvline(mark, color="tab:red", ls="--", lw=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("elements")
    ax.set_title(title, loc="left")
    return png(fig)


def sample_chart(samples: Sequence[str], residual_um: np.ndarray, verdicts: Sequence[str]) -> bytes:
    """The batch at a glance: each sample's median target residual after refinement (um), the bar
    coloured by its weld verdict (pass green, fail red, otherwise grey)."""
    colours = {"pass": "tab:green", "fail": "tab:red"}
    n = len(samples)
    fig = _figure(7.5, 0.6 + 0.22 * max(n, 1))
    ax = fig.add_subplot()
    y = np.arange(n)
    ax.barh(y, residual_um, color=[colours.get(v, "0.6") for v in verdicts])
    ax.set_yticks(y, labels=list(samples), fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("median target residual after refinement, um (bar colour: the weld's verdict)")
    ax.grid(axis="x", alpha=0.3)
    return png(fig)


def stress_along_toes(factors: Sequence[tuple[str, np.ndarray, np.ndarray]],
                      radii: Sequence[tuple[str, np.ndarray, np.ndarray]], *, hot: tuple[float, float] | None,
                      notch: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
                      drawn: dict[str, float] | None = None) -> bytes:
    """The stress concentration along each toe (``factors``: (label, positions mm, factors)) above
    the measured toe radius along the same toes (``radii``: (label, positions mm, radii mm)); the
    hot spot (position, factor) ringed; dashed, each toe's notch stress factor (``notch``, as
    ``factors``); dotted, the drawn weld's factor of each toe (``drawn``: label -> factor)."""
    fig = _figure(7.5, 3.6)
    top, bottom = fig.subplots(2, 1, sharex=True)
    palette = plt.get_cmap("tab10")
    drawn = drawn or {}
    labels = {f[0] for f in factors} | {r[0] for r in radii} | {n[0] for n in notch} | set(drawn)
    colour = {label: palette(k % 10) for k, label in enumerate(sorted(labels))}
    for label, pos, val in factors:
        top.plot(pos, val, "o-", ms=3, lw=0.8, color=colour[label], label=label)
    for label, pos, val in notch:
        top.plot(pos, val, "--", lw=0.8, color=colour[label])
    span = [min((float(p.min()) for _, p, _ in factors if len(p)), default=0.0),
            max((float(p.max()) for _, p, _ in factors if len(p)), default=1.0)]
    for label, value in sorted(drawn.items()):
        top.plot(span, [value, value], ":", lw=1.0, color=colour[label])
    if hot is not None:
        top.plot([hot[0]], [hot[1]], "o", ms=10, mfc="none", mec="tab:red", mew=1.2)
    for label, pos, val in radii:
        bottom.plot(pos, val, "-", lw=0.8, color=colour[label], label=label)
    top.set_ylabel("stress concentration")
    bottom.set_ylabel("toe radius, mm")
    bottom.set_xlabel("position along the weld line, mm")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    top.legend(loc="upper right", ncols=4, frameon=False)
    top.set_title("Stress concentration at each toe under axial tension (ringed: the hot spot)", loc="left")
    return png(fig)


def stress_field(points: np.ndarray, triangles: np.ndarray, factor: np.ndarray, *, toe: np.ndarray, title: str,
                 half_span_mm: float = 6.0) -> bytes:
    """The maximum principal stress over the nominal stress on a section model's triangles, within
    ``half_span_mm`` of the ``toe`` (x, y; mm), the toe marked."""
    fig = _figure(7.5, 3.4)
    ax = fig.add_subplot()
    x0, y0 = float(toe[0]), float(toe[1])
    near = np.all(np.abs(points[triangles].mean(axis=1) - [x0, y0]) < 1.5 * half_span_mm, axis=1)
    shown = ax.tripcolor(points[:, 0], points[:, 1], triangles[near], np.asarray(factor, np.float64), shading="gouraud",
                         cmap="inferno", vmin=0.0)
    ax.plot([x0], [y0], "+", color="tab:cyan", ms=10)
    ax.set_xlim(x0 - half_span_mm, x0 + half_span_mm)
    ax.set_ylim(y0 - 0.5 * half_span_mm, y0 + 0.5 * half_span_mm)
    ax.set_aspect("equal")
    ax.set_xlabel("across the weld, mm")
    ax.set_ylabel("through the thickness, mm")
    fig.colorbar(shown, ax=ax, label="max principal / nominal")
    ax.set_title(title, loc="left")
    return png(fig)

