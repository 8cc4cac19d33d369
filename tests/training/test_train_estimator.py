"""The estimator's training script (training/train_estimator.py): a wider start from fewer lights."""

import torch

from torchbrdf.recovery.prior import MapEstimator
from training.train_estimator import widen_lights


def test_widened_estimator_starts_as_the_one_image_estimator():
    torch.manual_seed(0)
    one = MapEstimator(lights=1, width=8, depth=2).eval()
    four = MapEstimator(lights=4, width=8, depth=2)
    four.load_state_dict(widen_lights(one.state_dict(), 1, 4))
    four.eval()
    images = torch.rand(2, 4, 3, 12, 12) + 0.01
    pos = torch.tensor([[0.1, 0.05, 3.0], [1.5, 0.0, 2.0], [-1.0, 1.0, 2.0], [0.0, -1.5, 2.0]])
    inten = torch.tensor([[15.0] * 3] + [[30.0] * 3] * 3)
    # The flash's channels and the pixel coordinates keep their weights; the new images add nothing yet.
    torch.testing.assert_close(four(images, pos, inten), one(images[:, :1], pos[:1], inten[:1]))
    other = images.clone()
    other[:, 1:] = torch.rand(2, 3, 3, 12, 12)
    torch.testing.assert_close(four(other, pos, inten), four(images, pos, inten))
