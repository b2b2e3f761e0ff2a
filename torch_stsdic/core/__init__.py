"""The subset solver: settings, status codes, shape functions, subset windows, B-spline images,
initial guesses, the Gauss-Newton formulations and batches, the predicted uncertainty and noise
theory, the specimen's shared motion model, argument checks.

Layer 1: imports only from :mod:`torch_stsdic.kernels`."""
