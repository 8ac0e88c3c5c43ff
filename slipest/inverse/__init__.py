"""Slip inverses: one leg cycle's features to slip (and what they need of the soil).

* :mod:`slipest.inverse.base`: the small interface (:class:`~slipest.inverse.base.SlipInverse`,
  :class:`~slipest.inverse.base.Soil`);
* :mod:`slipest.inverse.eq515`: thesis Eq. 5.15 exactly as stated (baseline), and its
  recursive use to learn ``dphi`` from reference slips;
* :mod:`slipest.inverse.surrogate`: the multi-feature inverse (a surrogate of the feature
  vector as a function of slip and soil, inverted by Bayes; works with the soil unknown),
  package data ``slipest/data/inverse_model.npz`` from ``tools/train_inverse.py``;
* :mod:`slipest.inverse.grid_kernels`: its compiled soil-grid kernels (cell likelihoods, slip
  marginal, whitening), shared with the recursive estimator;
* :mod:`slipest.inverse.simdata`: simulated feature rows for training and checks.

The recursive estimator over cycles is :mod:`slipest.estimator`; the API a rover
program calls is :mod:`slipest.online`.
"""
