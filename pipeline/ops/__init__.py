"""Torch building blocks below the medium, training and evaluation: the photometric losses and SSIM (with its numba
twin), PSNR and the other image metrics, and the compiled-graph helpers."""
