"""Stage 4: PBR material and light decomposition on fixed surfels (paper Sec. IV-C2).

Per-surfel albedo, roughness and metallic, a white directional light map L_dir over the
128-direction grid and an indirect light (per-surfel RGB SH of degree 2) are fitted to the
training images by Adam on the loss of Eq. 18:

    L = L_rend + l_ind2 |L_ind|^2 + l_tv TV(L_ind) + l_brdf TV(a, rho, m) + l_reg E[1 - rho + m]

with deferred, image-space shading of Eq. 17 (``shading``) and the pixelwise visibility
V [H, W, L] of ``visibility`` (shadow maps of the surfels' own depth, rendered once per
direction and shared by every view; the view points are the surfels' rasterized expected
depth and normals). After each step the albedo is replaced by its mean over the surfel's
segment (the hard constraint; the "segment" channel is an integer id per surfel).
``cpu-small`` and ``cpu-medium`` then leave the albedo's TV out (with the constraint it acts
only across segment borders, where it merged the segments' colours) and hold the albedo x
light scale, which the images leave free, by rescaling albedo, light and indirect light
together (``hold_albedo_scale``): otherwise the albedo drifted to its box at 1.

Only what the scene needs is modelled: after ``warmup`` steps the grid directions are
grouped into lights (``merge_directions``) and the lights carrying less than
``prune_threshold`` times the strongest one's irradiance are dropped (``prune_lights``; no
shadow maps, no shading for them; their L_dir is 0 from then on), and with
``specular="auto"`` the GGX lobe is switched off when the fitted parameters say the scene is
diffuse (every surfel's metallic below ``auto_metallic_max`` and roughness above
``auto_roughness_min`` at the end of the warm-up; the lobe then costs nothing and metallic
is fixed at 0). ``cpu-small`` and ``cpu-medium`` model no lobe at all (``specular="off"``).
Why each default that is not the paper's is what it is: docs/decisions.md.

Where the light is: the grid's neighbouring directions that share a light merge into one at
their energy-weighted direction (``merge_directions``), which lands a few degrees off, and
``refine_directions`` then searches each light's direction on a local grid, scoring a
candidate by the training views' squared error with its shadow map rendered and its
irradiance re-fitted in closed form (shadows are the sharpest cue); ``refine_score``
says what else is re-fitted with it (cpu-small: each segment's albedo, so that the
materials fitted under the current lights do not hold a light where they were fitted).
The first refinement can start each light with a global pass over the hemisphere
(``refine_global``, off by default: see there), so a light merged into the wrong cell is
found again; after each refinement the lights that met merge and those that carry little
irradiance and explain little of the views are dropped (``settle_lights``: backward
elimination with a joint non-negative least-squares re-fit of the others' irradiance).

Where the normals are (not in the paper): stage 1 fits colours, not shading, so its normals
on parts a few pixels across are smooth, and the attached shadows on their far sides go.
With ``normal_steps`` > 0 a last phase holds everything fitted and moves each surfel's
shading normal to explain the views' shading, pulled toward stage 2's normal
(``normal_step``); relighting and evaluation shade with them.

Where a segment is textured (not in the paper; off in every preset): with ``detail_prior``
> 0 each surfel's albedo is its segment's times a bounded per-surfel factor, fitted from the
second refinement on, away from the fitted shadows' edges (``start_detail``); the result's
albedo channel holds the product.

Modules, by job: ``config`` (settings, presets), ``channels`` (initial values, projection),
``views`` (training views, per-view maps and loss), ``scoring`` (closed-form light scores),
``lights`` (merge, prune, refine, settle), ``state`` (light model, state, checkpoint,
result), ``normals`` (the normal phase), ``fit`` (the loop), ``outputs`` (the fit's files)
and ``runner`` (stage 4 on a dataset, fitted or read back).
"""

from __future__ import annotations

from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.fit import fit_material
from mi_shadowgs.stages.material.outputs import fit_from_files, light_json
from mi_shadowgs.stages.material.runner import (
    decompose,
    fit_or_reuse,
    occluder_bounds,
)
from mi_shadowgs.stages.material.state import MaterialResult, MaterialState

__all__ = [
    "MaterialConfig",
    "MaterialResult",
    "MaterialState",
    "decompose",
    "fit_from_files",
    "fit_material",
    "fit_or_reuse",
    "light_json",
    "occluder_bounds",
]
