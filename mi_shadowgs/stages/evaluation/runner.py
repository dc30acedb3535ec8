"""The evaluation of one fitted variant of a run (``mi_shadowgs.pipeline`` calls it after
stage 4): metrics on the test views, the report's figures, for the full fit the relit
previews, written into the variant's output folder.
"""

from __future__ import annotations

from mi_shadowgs.io.atomic import write_json
from mi_shadowgs.stages.evaluation.evaluate import evaluate_decomposition
from mi_shadowgs.stages.evaluation.figures import figure_picks, write_figures
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.relight.previews import write_previews
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds, VisibilityConfig


def evaluate_variant(out, result, train, test, bounds: SceneBounds,
                     vis_config: VisibilityConfig, relight_config: relight.RelightConfig,
                     figure_views: int, segments: dict | None = None,
                     fit_s: float | None = None, preview_envmaps=None) -> dict:
    """Evaluate stage 4's ``result`` (a ``MaterialResult``) on ``test`` and write
    ``metrics.json``, ``grid.json`` and ``figures/`` into ``out`` (an open
    ``io.provenance.Output``; the caller finishes it). Returns the metrics.

    ``vis_config``: the shadow maps stage 4 fitted with; ``relight_config``: the relightings'
    env-map sampling; ``figure_views``: how many test views the figures show; ``segments``:
    stage 2's segment maps (view stem -> sRGB uint8); ``fit_s``: the fit's seconds, recorded
    in the metrics; ``preview_envmaps`` ((name, file, scale), as ``write_previews`` takes
    them): None for no relit previews, else previews of the first test view under the light
    turntable and these env maps.
    """
    cache = relight.RelightCache()  # shadow maps shared by evaluation and previews
    metrics, images = evaluate_decomposition(result, train, test, bounds, vis_config,
                                             relight_config, cache=cache)
    metrics["fit_s"] = fit_s
    with out.staged("figures") as tmp:  # beside any file of the user's there
        grid = write_figures(tmp, test, images, figure_views, segments)
        if preview_envmaps is not None:  # relit under standard lights (no ground truth)
            cameras = [test.cameras[i] for i in figure_picks(len(test), 1)]
            grid["previews"] = write_previews(tmp, result, cameras, bounds, vis_config,
                                              relight_config, preview_envmaps, cache)
    write_json(out.path("grid.json"), grid)
    write_json(out.path("metrics.json"), metrics)
    return metrics
