//! Eight f32 lanes for the compositing kernels, one implementation per
//! instruction set, and the choice between them at run time.
//!
//! The kernels in [`super::raster`] are generic over [`Lanes`]. [`Kernels`]
//! names the instruction set they run with: AVX-512 and AVX2 (both on 256-bit
//! registers; AVX-512VL adds mask registers and more vector registers), or the
//! portable lanes, plain arrays the compiler vectorizes for whatever the build
//! targets (SSE, NEON). The AVX entry points are compiled with
//! `#[target_feature]`, so one binary built for a baseline CPU runs everywhere
//! and uses the vector units the CPU it runs on has.

use std::ops::{Add, AddAssign, BitAnd, BitOr, Div, Mul, Neg, Not, Sub};
use std::sync::OnceLock;

/// Lanes per vector: eight adjacent pixels of one tile row.
pub const LANES: usize = 8;

/// Asks the CPU to bring `value`'s cache line in ahead of its use: the
/// compositing loops read Gaussians scattered over megabytes, in an order known
/// in advance. A hint only; nothing on other architectures than x86-64.
#[inline(always)]
pub fn prefetch<T>(value: &T) {
    // SAFETY: a prefetch never faults or changes memory; SSE is in every x86-64 CPU.
    #[cfg(target_arch = "x86_64")]
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>((value as *const T).cast())
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// Eight f32 aligned to 32 bytes, what the kernels load and store whole.
/// Aligned, a 256-bit access stays one instruction: for unaligned ones, builds
/// tuned for a generic CPU (as the portable binary is) emit two 128-bit halves.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub struct Block(pub [f32; LANES]);

/// Eight f32 lanes. Masks are lanes with every bit set (true) or clear
/// (false), as the comparisons return them. Every implementation computes the
/// same IEEE operations lane by lane, and [`Lanes::reduce_add`] adds in one
/// fixed order, so the kernel sets differ only where FMA fuses a product and
/// a sum.
pub trait Lanes:
    Copy
    + Add<Output = Self>
    + AddAssign
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + BitAnd<Output = Self>
    + BitOr<Output = Self>
    + Not<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    /// 0, 1, ..., 7.
    const INDEX: Self;

    fn splat(x: f32) -> Self;
    fn load(a: &Block) -> Self;
    fn store(self, a: &mut Block);
    fn to_array(self) -> [f32; LANES] {
        let mut a = Block::default();
        self.store(&mut a);
        a.0
    }
    /// self * b + c, fused where the kernel set has FMA.
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// c - self * b, fused where the kernel set has FMA.
    fn mul_neg_add(self, b: Self, c: Self) -> Self;
    /// Lane minimum; `other` where either is NaN (x86's minps).
    fn min(self, other: Self) -> Self;
    /// Lane maximum; `other` where either is NaN (x86's maxps).
    fn max(self, other: Self) -> Self;
    fn sqrt(self) -> Self;
    fn floor(self) -> Self;
    fn ceil(self) -> Self;
    /// To the nearest integer, ties to even.
    fn round(self) -> Self;
    /// 2^n for lanes holding integers n in [-126, 127] (built from exponent bits).
    fn exp2_integral(self) -> Self;
    fn cmp_lt(self, other: Self) -> Self;
    fn cmp_le(self, other: Self) -> Self;
    fn cmp_gt(self, other: Self) -> Self;
    fn cmp_ge(self, other: Self) -> Self;
    /// Per lane, `if_true` where `self` (a mask) is set, else `if_false`.
    fn select(self, if_true: Self, if_false: Self) -> Self;
    /// Bit j = lane j of the mask.
    fn move_mask(self) -> u32;
    fn none(self) -> bool {
        self.move_mask() == 0
    }
    /// Sum of the lanes as ((0+4) + (2+6)) + ((1+5) + (3+7)), the same order in every kernel set.
    fn reduce_add(self) -> f32;
}

/// Pairwise sums in the order [`Lanes::reduce_add`] promises.
#[inline(always)]
fn reduce_in_order(a: [f32; LANES]) -> f32 {
    let s = [a[0] + a[4], a[1] + a[5], a[2] + a[6], a[3] + a[7]];
    (s[0] + s[2]) + (s[1] + s[3])
}

/// The portable lanes: an array the compiler vectorizes for the build target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Portable([f32; LANES]);

impl Portable {
    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> Self {
        Self(self.0.map(f))
    }

    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        Self(std::array::from_fn(|i| f(self.0[i], o.0[i])))
    }

    #[inline(always)]
    fn bits(self, o: Self, f: impl Fn(u32, u32) -> u32) -> Self {
        self.zip(o, |a, b| f32::from_bits(f(a.to_bits(), b.to_bits())))
    }

    #[inline(always)]
    fn mask(self, o: Self, f: impl Fn(f32, f32) -> bool) -> Self {
        self.zip(o, |a, b| f32::from_bits(if f(a, b) { u32::MAX } else { 0 }))
    }
}

macro_rules! portable_op {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for Portable {
            type Output = Self;
            #[inline(always)]
            fn $method(self, o: Self) -> Self {
                self.zip(o, |a, b| a $op b)
            }
        }
    };
}
portable_op!(Add, add, +);
portable_op!(Sub, sub, -);
portable_op!(Mul, mul, *);
portable_op!(Div, div, /);

impl AddAssign for Portable {
    #[inline(always)]
    fn add_assign(&mut self, o: Self) {
        *self = *self + o;
    }
}

impl Neg for Portable {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        self.map(|a| -a)
    }
}

impl BitAnd for Portable {
    type Output = Self;
    #[inline(always)]
    fn bitand(self, o: Self) -> Self {
        self.bits(o, |a, b| a & b)
    }
}

impl BitOr for Portable {
    type Output = Self;
    #[inline(always)]
    fn bitor(self, o: Self) -> Self {
        self.bits(o, |a, b| a | b)
    }
}

impl Not for Portable {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        self.map(|a| f32::from_bits(!a.to_bits()))
    }
}

impl Lanes for Portable {
    const ZERO: Self = Self([0.0; LANES]);
    const ONE: Self = Self([1.0; LANES]);
    const INDEX: Self = Self([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);

    #[inline(always)]
    fn splat(x: f32) -> Self {
        Self([x; LANES])
    }
    #[inline(always)]
    fn load(a: &Block) -> Self {
        Self(a.0)
    }
    #[inline(always)]
    fn store(self, a: &mut Block) {
        a.0 = self.0;
    }
    // Unfused: without FMA hardware f32::mul_add is a slow library call.
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        self * b + c
    }
    #[inline(always)]
    fn mul_neg_add(self, b: Self, c: Self) -> Self {
        c - self * b
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        self.zip(o, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.zip(o, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        self.map(f32::sqrt)
    }
    #[inline(always)]
    fn floor(self) -> Self {
        self.map(f32::floor)
    }
    #[inline(always)]
    fn ceil(self) -> Self {
        self.map(f32::ceil)
    }
    #[inline(always)]
    fn round(self) -> Self {
        self.map(f32::round_ties_even)
    }
    #[inline(always)]
    fn exp2_integral(self) -> Self {
        self.map(|n| f32::from_bits(((n as i32 + 127) << 23) as u32))
    }
    #[inline(always)]
    fn cmp_lt(self, o: Self) -> Self {
        self.mask(o, |a, b| a < b)
    }
    #[inline(always)]
    fn cmp_le(self, o: Self) -> Self {
        self.mask(o, |a, b| a <= b)
    }
    #[inline(always)]
    fn cmp_gt(self, o: Self) -> Self {
        self.mask(o, |a, b| a > b)
    }
    #[inline(always)]
    fn cmp_ge(self, o: Self) -> Self {
        self.mask(o, |a, b| a >= b)
    }
    #[inline(always)]
    fn select(self, t: Self, f: Self) -> Self {
        let m = self;
        (m & t) | (!m & f)
    }
    #[inline(always)]
    fn move_mask(self) -> u32 {
        self.0.iter().enumerate().fold(0, |m, (i, a)| m | ((a.to_bits() >> 31) << i))
    }
    #[inline(always)]
    fn reduce_add(self) -> f32 {
        reduce_in_order(self.0)
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use x86::Avx;

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::{reduce_in_order, Block, Lanes, LANES};
    use std::ops::{Add, AddAssign, BitAnd, BitOr, Div, Mul, Neg, Not, Sub};

    /// Lanes in one 256-bit AVX register.
    ///
    /// Safety: every method runs AVX2/FMA instructions. Values of this type
    /// exist only inside the kernel entry points of [`super::Kernels`] that
    /// are compiled with those features and entered after the CPU was found
    /// to have them; the type is private to the crate, and nothing else in
    /// it names the type.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx(__m256);

    macro_rules! avx_op {
        ($trait:ident, $method:ident, $intrinsic:ident) => {
            impl $trait for Avx {
                type Output = Self;
                #[inline(always)]
                fn $method(self, o: Self) -> Self {
                    // SAFETY: see the type's documentation.
                    Self(unsafe { $intrinsic(self.0, o.0) })
                }
            }
        };
    }
    avx_op!(Add, add, _mm256_add_ps);
    avx_op!(Sub, sub, _mm256_sub_ps);
    avx_op!(Mul, mul, _mm256_mul_ps);
    avx_op!(Div, div, _mm256_div_ps);
    avx_op!(BitAnd, bitand, _mm256_and_ps);
    avx_op!(BitOr, bitor, _mm256_or_ps);

    impl AddAssign for Avx {
        #[inline(always)]
        fn add_assign(&mut self, o: Self) {
            *self = *self + o;
        }
    }

    impl Neg for Avx {
        type Output = Self;
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_xor_ps(self.0, _mm256_set1_ps(-0.0)) })
        }
    }

    impl Not for Avx {
        type Output = Self;
        #[inline(always)]
        fn not(self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_xor_ps(self.0, _mm256_castsi256_ps(_mm256_set1_epi32(-1))) })
        }
    }

    macro_rules! avx_round {
        ($self:ident, $mode:expr) => {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_round_ps::<{ $mode | _MM_FROUND_NO_EXC }>($self.0) })
        };
    }

    macro_rules! avx_cmp {
        ($self:ident, $o:ident, $pred:ident) => {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_cmp_ps::<$pred>($self.0, $o.0) })
        };
    }

    const fn lanes(a: [f32; LANES]) -> Avx {
        // SAFETY: __m256 is eight f32 lanes, in order.
        Avx(unsafe { std::mem::transmute::<[f32; LANES], __m256>(a) })
    }

    impl Lanes for Avx {
        const ZERO: Self = lanes([0.0; LANES]);
        const ONE: Self = lanes([1.0; LANES]);
        const INDEX: Self = lanes([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);

        #[inline(always)]
        fn splat(x: f32) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_set1_ps(x) })
        }
        #[inline(always)]
        fn load(a: &Block) -> Self {
            // SAFETY: `a` is eight f32 aligned to 32 bytes; see the type's documentation.
            Self(unsafe { _mm256_load_ps(a.0.as_ptr()) })
        }
        #[inline(always)]
        fn store(self, a: &mut Block) {
            // SAFETY: `a` is eight f32 aligned to 32 bytes; see the type's documentation.
            unsafe { _mm256_store_ps(a.0.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn mul_add(self, b: Self, c: Self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_fmadd_ps(self.0, b.0, c.0) })
        }
        #[inline(always)]
        fn mul_neg_add(self, b: Self, c: Self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_fnmadd_ps(self.0, b.0, c.0) })
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_min_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_max_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_sqrt_ps(self.0) })
        }
        #[inline(always)]
        fn floor(self) -> Self {
            avx_round!(self, _MM_FROUND_TO_NEG_INF)
        }
        #[inline(always)]
        fn ceil(self) -> Self {
            avx_round!(self, _MM_FROUND_TO_POS_INF)
        }
        #[inline(always)]
        fn round(self) -> Self {
            avx_round!(self, _MM_FROUND_TO_NEAREST_INT)
        }
        #[inline(always)]
        fn exp2_integral(self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe {
                let n = _mm256_add_epi32(_mm256_cvtps_epi32(self.0), _mm256_set1_epi32(127));
                _mm256_castsi256_ps(_mm256_slli_epi32::<23>(n))
            })
        }
        #[inline(always)]
        fn cmp_lt(self, o: Self) -> Self {
            avx_cmp!(self, o, _CMP_LT_OQ)
        }
        #[inline(always)]
        fn cmp_le(self, o: Self) -> Self {
            avx_cmp!(self, o, _CMP_LE_OQ)
        }
        #[inline(always)]
        fn cmp_gt(self, o: Self) -> Self {
            avx_cmp!(self, o, _CMP_GT_OQ)
        }
        #[inline(always)]
        fn cmp_ge(self, o: Self) -> Self {
            avx_cmp!(self, o, _CMP_GE_OQ)
        }
        #[inline(always)]
        fn select(self, t: Self, f: Self) -> Self {
            // SAFETY: see the type's documentation.
            Self(unsafe { _mm256_blendv_ps(f.0, t.0, self.0) })
        }
        #[inline(always)]
        fn move_mask(self) -> u32 {
            // SAFETY: see the type's documentation.
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        fn reduce_add(self) -> f32 {
            reduce_in_order(self.to_array())
        }
    }
}

/// The instruction set the compositing kernels run with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Isa {
    #[cfg(target_arch = "x86_64")]
    Avx512,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    Portable,
}

static ACTIVE: OnceLock<Kernels> = OnceLock::new();

/// A kernel set the CPU this process runs on can execute: only [`Kernels::best`],
/// [`Kernels::available`] and [`Kernels::named`] make one, after checking the CPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Kernels(Isa);

impl Kernels {
    /// Every kernel set this CPU can run, fastest first.
    pub fn available() -> Vec<Kernels> {
        let mut sets = Vec::new();
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            let avx2 = has!("avx2") && has!("fma");
            if avx2 && has!("avx512f") && has!("avx512vl") && has!("avx512bw") && has!("avx512dq") {
                sets.push(Kernels(Isa::Avx512));
            }
            if avx2 {
                sets.push(Kernels(Isa::Avx2));
            }
        }
        sets.push(Kernels(Isa::Portable));
        sets
    }

    /// The fastest kernel set this CPU runs.
    pub fn best() -> Kernels {
        Self::available()[0]
    }

    /// The kernel set every render of this process uses: [`Kernels::best`]
    /// unless [`Kernels::make_active`] chose another before the first render.
    pub fn active() -> Kernels {
        *ACTIVE.get_or_init(Self::best)
    }

    /// Makes `self` the kernel set of this process (e.g. to measure the
    /// portable kernels on an AVX2 machine). Fails with the set in use when a
    /// render has already chosen one.
    pub fn make_active(self) -> Result<(), Kernels> {
        match ACTIVE.set(self) {
            Err(_) if Self::active() != self => Err(Self::active()),
            _ => Ok(()),
        }
    }

    /// The kernel set called `name` (`avx512`, `avx2`, `portable`), if this CPU runs it.
    pub fn named(name: &str) -> Result<Kernels, String> {
        let all = Self::available();
        all.iter().copied().find(|k| k.name() == name).ok_or_else(|| {
            let names: Vec<&str> = all.iter().map(|k| k.name()).collect();
            format!("kernel set '{name}' is not available on this CPU (available: {})", names.join(", "))
        })
    }

    pub fn name(self) -> &'static str {
        match self.0 {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => "avx512",
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => "avx2",
            Isa::Portable => "portable",
        }
    }

    /// What the kernels execute as, for benchmark reports.
    pub fn description(self) -> &'static str {
        match self.0 {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => "8 lanes in one 256-bit register, AVX-512VL masks (avx512f/vl/bw/dq, avx2, fma)",
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => "8 lanes in one 256-bit register (avx2, fma)",
            Isa::Portable => "8 lanes as arrays vectorized for the build target",
        }
    }

    pub(crate) fn isa(self) -> Isa {
        self.0
    }
}

/// Runs `$body` compiled for the kernel set `$kernels`, with the lanes type
/// named `$L` bound to that set's lanes. The body becomes the body of a nested
/// function taking `$arg: $ty` (`#[target_feature]` for the AVX sets), so the
/// generic, `#[inline(always)]` kernel code it calls is compiled for those
/// features; the portable set runs it as compiled for the build target.
macro_rules! dispatch {
    ($kernels:expr, |$L:ident; $($arg:ident: $ty:ty),*| -> $ret:ty $body:block) => {{
        match $kernels.isa() {
            #[cfg(target_arch = "x86_64")]
            $crate::render::lanes::Isa::Avx512 => {
                #[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512bw,avx512dq")]
                unsafe fn run($($arg: $ty),*) -> $ret {
                    type $L = $crate::render::lanes::Avx;
                    $body
                }
                // SAFETY: this kernel set exists only where the CPU has these features.
                unsafe { run($($arg),*) }
            }
            #[cfg(target_arch = "x86_64")]
            $crate::render::lanes::Isa::Avx2 => {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn run($($arg: $ty),*) -> $ret {
                    type $L = $crate::render::lanes::Avx;
                    $body
                }
                // SAFETY: this kernel set exists only where the CPU has these features.
                unsafe { run($($arg),*) }
            }
            $crate::render::lanes::Isa::Portable => {
                fn run($($arg: $ty),*) -> $ret {
                    type $L = $crate::render::lanes::Portable;
                    $body
                }
                run($($arg),*)
            }
        }
    }};
}
pub(crate) use dispatch;
