//! Run-time dispatch of the element-wise passes to AVX2.

/// Defines `$name`, which runs `$generic` (an `#[inline(always)]` function of the same
/// arguments) compiled for AVX2 where the CPU has it, detected at run time, and as compiled
/// for the baseline otherwise. The element-wise passes (the Winograd transforms, pooling) are plain loops over channel vectors that the compiler vectorises
/// for the lanes it may use; this gives them AVX2's.
macro_rules! with_avx2 {
    ($(#[$doc:meta])* fn $name:ident = $generic:ident($($arg:ident: $ty:ty),* $(,)?)) => {
        $(#[$doc])*
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) {
                    $generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2 (checked just above).
                    return unsafe { avx2($($arg),*) };
                }
            }
            $generic($($arg),*)
        }
    };
}

pub(crate) use with_avx2;
