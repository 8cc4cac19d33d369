"""Screen-space shading: g-buffers, lights, per-pixel shading and environment integration.

``gbuffer`` (:class:`GBuffer`), ``geometry`` (analytic sphere/plane g-buffers, pinhole rays),
``lights`` (point, directional, environment), ``shading`` (:func:`shade`, :func:`plan`),
``envmap`` (Monte Carlo and split-sum environment integration) and ``sampling`` (BRDF and
lat-long map importance sampling).

May import: ``torchbrdf._math``, ``torchbrdf._checks``, ``torchbrdf.io``, ``torchbrdf.brdf``
and ``torchbrdf.kernels``.  Never ``analysis``, ``capture`` or ``recovery``.
"""
