"""Images as arrays: the 14 differentiable augmentations and their filters, a differentiable JPEG,
quality metrics (PSNR, SSIM, LPIPS) and image losses (BCE on logits, Watson-DCT, VGG, SSIM, TV)."""
