"""Reflectance models and the microfacet pieces they are built from.

Fresnel terms (``fresnel``), normal distributions (``distributions``), masking-shadowing
(``masking``), diffuse lobes (``diffuse``), frames (``frames``) and the models composed from
them: ``principled`` (Disney 2012/2014), ``smits`` (Pixar Wall-E/Up), ``svbrdf_ggx`` (the
SVBRDF-capture GGX), ``microfacet`` (any D·F·G by name), ``lambert`` and ``measured`` (MERL);
``capture_residual`` runs a capture fit's log residual on the fused kernels (or eagerly).

May import: ``torchbrdf._math``, ``torchbrdf._checks``, ``torchbrdf.io`` and, for the fused
fast path, ``torchbrdf.kernels`` (lazily, at dispatch).  Never ``render``, ``analysis``,
``capture`` or ``recovery``.  The public names are re-exported by :mod:`torchbrdf`.
"""
