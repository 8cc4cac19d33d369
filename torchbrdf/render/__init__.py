"""Screen-space shading: g-buffers, lights, per-pixel shading and environment integration.

``gbuffer`` (:class:`GBuffer`), ``geometry`` (analytic sphere/plane g-buffers, pinhole rays),
``lights`` (point, directional, environment), ``shading`` (:func:`shade`, :func:`plan`,
:class:`Shader`), ``prepare`` (shade's steps before any pass: validate, select pixels, inspect
the material, schedule), ``shading_plan`` (:class:`ShadingPlan`, what a call will compute),
``passes`` (one checkpointed per-light pass), ``fused_lights`` (every point and directional
light in one fused kernel pass), ``env`` (Monte Carlo and split-sum environment integration,
one module per concept; ``envmap`` re-exports its public names) and ``sampling`` (BRDF and
lat-long map importance sampling).

Within the package imports run one way: ``shading`` imports ``prepare``, ``shading_plan``,
``passes``, ``fused_lights`` and ``env``; ``env`` imports ``sampling``; nothing imports ``shading``.

May import: ``torchbrdf._math``, ``torchbrdf._checks``, ``torchbrdf.io``, ``torchbrdf.brdf``
and ``torchbrdf.kernels``.  Never ``analysis``, ``capture`` or ``recovery``.
"""
