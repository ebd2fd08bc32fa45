"""Tests of nodes.stabilize.lbfgs."""

import numpy as np
import torch
from scipy.optimize import rosen, rosen_der

from nodes.stabilize.lbfgs import lbfgs


def test_lbfgs_minimises_rosenbrock():
    def fun(x):
        xn = x.numpy()
        return float(rosen(xn)), torch.tensor(rosen_der(xn))
    x, f, iters = lbfgs(fun, torch.tensor([-1.2, 1.0, -0.5, 0.8], dtype=torch.float64), iterations=200)
    assert f < 1e-10 and iters <= 200
    np.testing.assert_allclose(x.numpy(), 1.0, atol=1e-5)
