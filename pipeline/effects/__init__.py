"""The catalogue of left-out physics (docs/physics.md "the effect catalogue"): one module per effect, each holding its
simulation, its fit terms, its explanation and its properties (:mod:`pipeline.effects.base`); the catalogue by id
and the CLI syntax in :mod:`pipeline.effects.catalogue`; the extended model (a thermal model plus fitted effects,
what ``diagnose`` writes into a passport and the passport layer and ``apply`` read) in
:mod:`pipeline.effects.model`."""
