"""The paper's figures from MLflow runs: Fig. 2, Fig. 3 and Fig. 4.

* **Fig. 2** (extrapolation error vs ``cos(s, ĝ)``, in-distribution vs OOD, PT vs SPOT):
  :func:`extrapolation_bins` reads each PT/SPOT run's binned error, from its
  ``extrapolation_error.json`` artifact (bin edges, mean error and counts per group) or, for runs
  without it, from the ``diag/extrap_bin_in`` / ``diag/extrap_bin_ood`` metrics (step = bin
  index; the edges are then unknown and the x-axis is the bin index). :func:`summarize_extrapolation`
  averages over runs (seeds) per method, group and bin index: mean of the runs' per-bin means,
  std across runs, the x position being the mean of the runs' bin centres (each run bins its own
  ``[min, max]`` of ``cos``, so centres differ slightly between runs). :func:`plot_fig2` draws
  panel (a) PT in-distribution vs OOD and panel (b) OOD for every method, with ±std bands.
* **Fig. 3** (a state beside its predicted subgoal): :func:`render_state_and_subgoal` renders two
  observation vectors of a gymnasium MuJoCo locomotion env (Hopper-v5, Walker2d-v5,
  HalfCheetah-v5) offscreen. The observation leaves out the x position (``obs = [qpos[1:],
  qvel]``), so the state is ``qpos = [0, obs[:nq-1]]``, ``qvel = obs[nq-1:]``. The caller gets ĝ
  from a CVAE (:func:`load_cvae` for a stage-cache entry, :func:`cvae_from_run` for the CVAE a
  run saved as its ``models/cvae`` artifact, + :func:`spot.subgoal.cvae.generate`).
* **Fig. 4** (PCA of observations and subgoals): every SPOT/PT run with diagnostics logs
  ``subgoal_projection.png``; :func:`fetch_artifact` copies it out of a run (:func:`save_image`
  writes it in the format of the output's extension), and :func:`projection_from_cvae` redraws it
  for a dataset from a CVAE.

Headless rendering: MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` when it is first imported;
:func:`spot.runtime.configure` (called by the ``spot`` command) sets ``MUJOCO_GL=egl`` if the
variable is unset and mujoco is not imported yet. EGL works with Mesa's software driver on machines without a GPU or
display (no
``/dev/dri`` needed); ``osmesa`` needs libOSMesa and ``glfw`` a display. If mujoco was already
imported with ``glfw`` and there is no display, set ``MUJOCO_GL=egl`` before starting Python.

Figures are drawn on bare :class:`matplotlib.figure.Figure` objects (Agg), never through pyplot.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from spot import SpotError, tracking
from spot.results import table_format, tables
from spot.results.figures_curves import image_format  # noqa: F401 (spot.figures.image_format: the CLI checks --out with it)

FIG2_ARTIFACT = "extrapolation_error.json"
FIG4_ARTIFACT = "subgoal_projection.png"
GROUPS = ("in_distribution", "ood")
GROUP_METRICS = {"in_distribution": "diag/extrap_bin_in", "ood": "diag/extrap_bin_ood"}
GROUP_LABELS = {"in_distribution": "in-distribution", "ood": "OOD"}
FIG2_METHODS = ("pt", "spot")
_LABELS = table_format.METHOD_LABELS


# --------------------------------------------------------------------------- Fig. 2
def _bins_from_artifact(path: Path) -> list[dict[str, Any]]:
    d = json.loads(path.read_text())
    edges = np.asarray(d["edges"], float)
    error, count = np.asarray(d["mean_error"], float), np.asarray(d["count"], float)
    centres = 0.5 * (edges[:-1] + edges[1:])
    rows = []
    for g, group in enumerate(d.get("groups", GROUPS)):
        for b in range(error.shape[1]):
            rows.append(
                {"group": group, "bin": b, "centre": centres[b], "mean_error": error[g, b], "count": count[g, b]}
            )
    return rows


def _bins_from_metrics(client: Any, run_id: str) -> list[dict[str, Any]]:
    rows = []
    for group, metric in GROUP_METRICS.items():
        for m in client.get_metric_history(run_id, metric):
            rows.append(
                {"group": group, "bin": int(m.step), "centre": np.nan, "mean_error": float(m.value), "count": np.nan}
            )
    return rows


def _pick(runs: pd.DataFrame, column: str, value: str | None, what: str) -> pd.DataFrame:
    if value is not None:
        runs = runs[runs[column] == value]
        if runs.empty:
            raise SpotError(f"no finished PT/SPOT run with {what} {value!r}")
        return runs
    options = sorted(runs[column].unique())
    if len(options) > 1:
        raise SpotError(f"runs of several {what}s ({', '.join(options)}); pick one (--{what.replace(' ', '-')})")
    return runs


def extrapolation_bins(
    runs: pd.DataFrame,
    tracking_uri: str | None = None,
    *,
    dataset: str | None = None,
    source: str | None = None,
    methods: Sequence[str] = FIG2_METHODS,
) -> pd.DataFrame:
    """Per-run binned extrapolation error of the finished ``methods`` runs of one dataset and source.

    Args:
      runs: a :func:`spot.results.load.load_runs` frame.
      tracking_uri: where the runs' artifacts and metric histories are read.
      dataset: the paper's dataset name (``paper_dataset`` column); needed if the runs span several.
      source: ``recipe`` or ``file``; needed if the runs span several (they are never mixed).
      methods: which methods to read.

    Returns:
      Rows ``run_id, method, seed, dataset, source, group, bin, centre, mean_error, count, origin``
      (``origin`` = ``artifact`` or ``metrics``; ``centre``/``count`` are NaN for ``metrics``).
    """
    sel = runs[(runs["status"] == "FINISHED") & runs["method"].isin(list(methods))]
    if sel.empty:
        raise SpotError(f"no finished run of {', '.join(methods)} to draw Fig. 2 from")
    sel = _pick(sel, "paper_dataset", dataset, "dataset")
    sel = _pick(sel, "dataset_source", source, "source")
    mixed = tables.mixed_params(sel, sel[["method"]])
    if mixed:
        raise SpotError(
            f"the {'/'.join(methods)} runs differ in more than the seed, so they are not pooled: "
            f"{'; '.join(mixed[:5])}; pick runs with --experiment / --sweep-id"
        )
    sel = sel.sort_values("start_time").drop_duplicates(["method", "seed"], keep="last")  # a re-run replaces
    client = tracking.reader(tracking_uri)
    uri = client.tracking_uri
    rows = []
    with tempfile.TemporaryDirectory(prefix="spot-fig2-") as tmp:
        for _, run in sel.iterrows():
            path = tracking.download_artifact(
                run["run_id"], run["artifact_uri"], FIG2_ARTIFACT, uri, str(Path(tmp) / run["run_id"])
            )
            found = _bins_from_artifact(path) if path is not None else _bins_from_metrics(client, run["run_id"])
            origin = "artifact" if path is not None else "metrics"
            rows += [
                {
                    "run_id": run["run_id"],
                    "method": run["method"],
                    "seed": run["seed"],
                    "dataset": run["paper_dataset"],
                    "source": run["dataset_source"],
                    **r,
                    "origin": origin,
                }
                for r in found
            ]
    if not rows:
        raise SpotError(
            "none of the selected runs logged extrapolation-error bins (PT runs need "
            "subgoal.diagnostics=true, SPOT runs log them always)"
        )
    return pd.DataFrame(rows)


def summarize_extrapolation(bins: pd.DataFrame, ddof: int = 1) -> pd.DataFrame:
    """Mean over runs per (method, group, bin): ``centre, mean_error, std, n_runs``.

    ``centre`` is the mean of the runs' bin centres, NaN if any run's edges are unknown.
    """
    g = bins.groupby(["method", "group", "bin"], sort=True)
    out = pd.DataFrame(
        {
            "centre": g["centre"].mean().where(g["centre"].count() == g["centre"].size()),
            "mean_error": g["mean_error"].mean(),
            "std": g["mean_error"].std(ddof=ddof),
            "n_runs": g["mean_error"].count(),
        }
    )
    return out.reset_index()


def _curve(ax: Any, s: pd.DataFrame, label: str, style: str, use_centres: bool) -> None:
    s = s.sort_values("bin")
    x = s["centre"] if use_centres else s["bin"]
    ax.plot(x, s["mean_error"], style, ms=3, label=label)
    std = s["std"].fillna(0.0)
    ax.fill_between(x, s["mean_error"] - std, s["mean_error"] + std, alpha=0.2)


def plot_fig2(bins: pd.DataFrame, path: str | Path, *, ddof: int = 1, reference: str = "pt") -> Path:
    """Fig. 2 as a PNG: (a) ``reference`` in-distribution vs OOD, (b) OOD of every method."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    summary = summarize_extrapolation(bins, ddof=ddof)
    use_centres = bool(summary["centre"].notna().all())
    methods = [
        m for m in (*FIG2_METHODS, *sorted(set(summary["method"]) - set(FIG2_METHODS))) if m in set(summary["method"])
    ]
    ref = reference if reference in methods else methods[0]
    fig = Figure(figsize=(9, 3.5))
    ax_a, ax_b = fig.subplots(1, 2, sharey=True)
    for group, style in (("in_distribution", "-o"), ("ood", "--s")):
        s = summary[(summary["method"] == ref) & (summary["group"] == group)]
        if not s.empty:
            _curve(ax_a, s, f"{_LABELS.get(ref, ref)} ({GROUP_LABELS[group]})", style, use_centres)
    for method in methods:
        s = summary[(summary["method"] == method) & (summary["group"] == "ood")]
        if not s.empty:
            _curve(ax_b, s, f"{_LABELS.get(method, method)} (OOD)", "-o" if method == ref else "--s", use_centres)
    n = bins.groupby("method")["run_id"].nunique()
    runs_note = ", ".join(f"{_LABELS.get(m, m)}: {n[m]} runs" for m in methods)
    ax_a.set_title(f"(a) {_LABELS.get(ref, ref)}: in-distribution vs OOD", fontsize=9)
    ax_b.set_title(f"(b) OOD ({runs_note})", fontsize=9)
    for ax in (ax_a, ax_b):
        ax.set_xlabel("cos(s, ĝ)" if use_centres else "cos(s, ĝ) bin (edges not logged)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    ax_a.set_ylabel("extrapolation error |z(r̂) − z(r)|")
    first = bins.iloc[0]
    fig.suptitle(f"{first['dataset']} ({first['source']}): mean ± std over runs", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


# --------------------------------------------------------------------------- Fig. 4
def save_image(png: str | Path, out: str | Path, dpi: int = 110) -> Path:
    """Write the PNG ``png`` to ``out`` in the format of its extension: a copy for ``.png``, else the
    image at its pixel size in a figure of that format (a raster inside a PDF or SVG)."""
    out = Path(out)
    fmt = image_format(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "png":
        shutil.copyfile(png, out)
        return out
    from matplotlib.image import imread

    img = imread(str(png))
    fig = Figure(figsize=(img.shape[1] / dpi, img.shape[0] / dpi), dpi=dpi)
    fig.figimage(img, resize=False)
    fig.savefig(out, dpi=dpi, format=fmt)
    return out


def fetch_artifact(run_id: str, artifact_path: str, out: str | Path, tracking_uri: str | None = None) -> Path:
    """Copy one artifact of a run (e.g. ``subgoal_projection.png``) to ``out``; a PNG is written in
    the format of ``out``'s extension (:func:`save_image`)."""
    is_png = artifact_path.lower().endswith(".png")
    if is_png:
        image_format(out)  # an unknown extension fails before the download
    client = tracking.reader(tracking_uri)
    uri = client.tracking_uri
    artifact_uri = tracking.artifact_uri(client, run_id)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="spot-artifact-") as tmp:
        got = tracking.download_artifact(run_id, artifact_uri, artifact_path, uri, tmp)
        if got is None:
            raise SpotError(f"run {run_id} has no artifact {artifact_path!r} (tracking URI {uri})")
        if is_png:
            save_image(got, out)
        else:
            shutil.copyfile(got, out)
    return out


def cvae_from_run(run_id: str, tracking_uri: str | None = None) -> tuple[Any, Any, dict[str, Any]]:
    """``(CVAE params, run config, the model's header)`` of a run that saved its CVAE
    (``models/cvae``: SPOT runs, and PT runs with the Fig. 2 diagnostics); the header's
    ``dataset`` is the run's dataset name (its evaluation env)."""
    from spot.subgoal import cvae as cvae_lib

    params, head = tracking.load_model(run_id, "cvae", tracking_uri)
    if not isinstance(params, cvae_lib.CVAEParams):
        raise SpotError(f"run {run_id}: models/cvae holds {type(params).__name__}, not CVAE params")
    return params, tracking.run_config(run_id, tracking_uri), head


def load_cvae(path: str | Path) -> Any:
    """CVAE params from a stage-cache entry (``cvae-<hash>.npz``, data only: never unpickled)."""
    from spot import cache
    from spot.subgoal import cvae as cvae_lib

    path = Path(path).expanduser()
    if not path.exists():
        raise SpotError(f"CVAE file {path} does not exist")
    try:
        value = cache.read_entry(path)
    except cache.EntryError as e:
        raise SpotError(f"{path} is not a stage-cache entry ({e}); expected $SPOT_CACHE_DIR/cvae-<hash>.npz") from None
    params = value["params"] if isinstance(value, dict) and "params" in value else value
    if not isinstance(params, cvae_lib.CVAEParams):
        raise SpotError(f"{path} holds {type(params).__name__}, not CVAE params")
    return params


def _check_dims(params: Any, observations: np.ndarray) -> None:
    obs_dim = int(params.obs_mean.shape[-1])
    if observations.shape[1] != obs_dim:
        raise SpotError(
            f"the CVAE was trained on {obs_dim}-D observations, the dataset has "
            f"{observations.shape[1]}-D ones: pick the CVAE of this dataset"
        )


def projection_from_cvae(params: Any, observations: np.ndarray, actions: np.ndarray, path: str | Path) -> Path:
    """Fig. 4-style PCA of ``observations`` and the CVAE's subgoals ĝ(s, a) for the same transitions."""
    from spot.subgoal import cvae as cvae_lib
    from spot.subgoal import diagnostics

    _check_dims(params, observations)
    generated = cvae_lib.generate(params, observations, actions)
    return diagnostics.plot_projection(observations, generated, path)


# --------------------------------------------------------------------------- Fig. 3
def _mujoco() -> Any:
    """mujoco, checked to have a GL backend that can render here."""
    import mujoco

    context = getattr(mujoco, "GLContext", None)
    backend = context.__module__.rsplit(".", 1)[-1] if context is not None else "disabled"
    if backend == "disabled" or (backend == "glfw" and not os.environ.get("DISPLAY")):
        raise SpotError(
            f"MuJoCo's GL backend is {backend!r} with no display; call "
            "spot.runtime.configure() (or set MUJOCO_GL=egl or osmesa) before anything imports mujoco"
        )
    return mujoco


def locomotion_env_id(name: str) -> str:
    """``Hopper-v5`` stays; a dataset name such as ``hopper-medium-expert`` -> its env id."""
    import gymnasium as gym

    from spot import envs

    if name in gym.registry:
        return name
    spec = envs.env_spec(name)
    if spec.family != "locomotion":
        raise SpotError(
            f"{name!r} is a {spec.family} dataset; Fig. 3 renders locomotion states only "
            f"(their observation maps to qpos/qvel)"
        )
    return spec.env_id


def observation_to_state(obs: np.ndarray, nq: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """``obs = [qpos[1:], qvel]`` (x position excluded) -> ``(qpos, qvel)`` with x = 0."""
    obs = np.asarray(obs, np.float64)
    if obs.shape != (nq - 1 + nv,):
        raise SpotError(
            f"observation has shape {obs.shape}; expected ({nq - 1 + nv},) = qpos[1:] ({nq - 1}) + qvel ({nv})"
        )
    return np.concatenate([[0.0], obs[: nq - 1]]), obs[nq - 1 :]


def render_observations(env_id: str, observations: np.ndarray, *, width: int = 320, height: int = 320) -> np.ndarray:
    """``[n, height, width, 3]`` uint8 images of observation vectors ``[n, obs_dim]``, one fixed side camera."""
    import gymnasium as gym

    mujoco = _mujoco()
    env_id = locomotion_env_id(env_id)
    observations = np.atleast_2d(np.asarray(observations, np.float64))
    env = gym.make(env_id)
    try:
        model = env.unwrapped.model
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = [0.0, 0.0, 0.8 * float(data.xpos[1][2])]  # body 1 = torso at qpos0
        camera.distance, camera.azimuth, camera.elevation = 2.8, 90.0, -5.0
        renderer = mujoco.Renderer(model, height, width)
        try:
            images = []
            for obs in observations:
                data.qpos[:], data.qvel[:] = observation_to_state(obs, model.nq, model.nv)
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=camera)
                images.append(renderer.render().copy())
        finally:
            renderer.close()
    finally:
        env.close()
    return np.stack(images)


def render_state_and_subgoal(
    env_id: str, obs: np.ndarray, subgoal: np.ndarray, path: str | Path, *, width: int = 320, height: int = 320
) -> Path:
    """Fig. 3 as a PNG: each state (left) beside its predicted subgoal ĝ (right).

    Args:
      env_id: ``Hopper-v5``, ``Walker2d-v5``, ``HalfCheetah-v5`` or a dataset name of those envs.
      obs, subgoal: ``[obs_dim]`` or ``[n, obs_dim]`` observation vectors (one row per pair).
      path: output PNG.
    """
    obs = np.atleast_2d(np.asarray(obs, np.float64))
    subgoal = np.atleast_2d(np.asarray(subgoal, np.float64))
    if obs.shape != subgoal.shape:
        raise SpotError(f"states {obs.shape} and subgoals {subgoal.shape} must have the same shape")
    images = render_observations(env_id, np.concatenate([obs, subgoal]), width=width, height=height)
    n = obs.shape[0]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(5.0, 2.6 * n))
    axes = np.atleast_2d(fig.subplots(n, 2))
    letters = "abcdefghijklmnopqrstuvwxyz"
    for i in range(n):
        for j, (image, what) in enumerate(((images[i], "state s"), (images[n + i], "predicted subgoal ĝ"))):
            ax = axes[i, j]
            ax.imshow(image)
            ax.set_axis_off()
            k = 2 * i + j
            ax.set_title(f"({letters[k % 26]}) {what}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def pairs_from_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(states, subgoals)`` from a ``.npy`` array of shape ``[2, obs_dim]`` or ``[n, 2, obs_dim]``."""
    pairs = np.load(Path(path).expanduser(), allow_pickle=False)
    if pairs.ndim == 2:
        pairs = pairs[None]
    if pairs.ndim != 3 or pairs.shape[1] != 2:
        raise SpotError(
            f"{path}: expected an array [2, obs_dim] or [n, 2, obs_dim] (state, subgoal), got {pairs.shape}"
        )
    return pairs[:, 0], pairs[:, 1]


def pairs_from_cvae(
    params: Any, observations: np.ndarray, actions: np.ndarray, indices: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """``(states, ĝ)`` for dataset transitions ``indices``: ĝ = the CVAE's prior-mean subgoal."""
    from spot.subgoal import cvae as cvae_lib

    _check_dims(params, observations)
    idx = np.asarray(indices, int)
    if idx.size == 0 or idx.min() < 0 or idx.max() >= len(observations):
        raise SpotError(f"indices must lie in [0, {len(observations)}), got {list(idx)}")
    return observations[idx], cvae_lib.generate(params, observations[idx], actions[idx])
