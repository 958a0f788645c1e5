"""Analysis: why the tracker is wrong and how a model fares, for a user reading the results.

- `diagnose`: which catalogue effect the model lacks, and the residual structure by feature;
- `features`: the per-pose features that structure is looked for along;
- `ledger`: every model fitted on a data set, kept beside the data;
- the report (`posecorr report`): `page` assembles the HTML, `figures` draws the plots,
  `interpretation` turns the diagnosis, the ledger and the worst poses into words;
  `screenshot` takes a picture of a page for the docs.

Nothing here is needed to apply a model (that is `posecorr.controller`); the diagnosis fits
models and needs the `train` extra, the report needs matplotlib.
"""
