//! GPU lifting on burn's cubecl backend: the host side of `texavatars_kernels::lift`.
//!
//! Forward, `global`: face frames → per-texel lift into the 13-channel payload → bilinear
//! blend at the samples (sigmoid on the opacity). `local`: face frames → blend of the 14
//! local channels → per-sample lift (sigmoid on the opacity).
//!
//! Backward, `global`: recompute the payload and its blend → sigmoid derivative → texels
//! gather their samples' gradients (CSR) → per-texel lift backward (local gradients written
//! channel-major, per-texel frame gradients) → faces gather their texels' frame gradients →
//! per-face frame backward → vertices gather their corners' and texels' anchor gradients.
//! `local`: blend → per-sample lift backward → texels, faces and vertices gather from the
//! samples. Every scatter is a CSR gather: no atomics, deterministic.
//!
//! The topology's index and CSR tables are uploaded once per device and kept with the
//! topology ([`BufferCache`]).

use burn::tensor::DType;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use texavatars_kernels::lift::blend::blend;
use texavatars_kernels::lift::bwd::frames::face_frames_backward;
use texavatars_kernels::lift::bwd::transform::lift_rows_backward;
use texavatars_kernels::lift::constants::{LOCAL_CHANNELS, OUT_CHANNELS};
use texavatars_kernels::lift::csr_gather::csr_gather;
use texavatars_kernels::lift::frames::face_frames;
use texavatars_kernels::lift::opacity_grad::opacity_grad;
use texavatars_kernels::lift::transform::lift_rows;

use std::sync::{Arc, Mutex};

use burn_cubecl::CubeDevice;

use crate::gpu::{Ctx, arg};
use crate::lift::tables::{Csr, GpuTables};
use crate::lift::{LiftMode, LiftParams};
use crate::texel::FrameKind;

/// A CSR list on the device.
struct CsrBuf {
    offsets: Handle,
    entries: Handle,
    weights: Handle,
    targets: usize,
    len: usize,
}

/// The topology's tables on one device.
struct Buffers {
    texel_from_samples: CsrBuf,
    face_from_texels: CsrBuf,
    face_from_samples: CsrBuf,
    vertex_from_texels: CsrBuf,
    vertex_from_samples: CsrBuf,
    vertex_from_corners: CsrBuf,
    faces: Handle,
    texel_frame: Handle,
    texel_corners: Handle,
    texel_bary: Handle,
    taps: Handle,
    tap_weights: Handle,
    sample_frame: Handle,
    sample_corners: Handle,
    sample_bary: Handle,
}

/// Per-device uploads of a topology's tables, kept by the [`crate::lift::Topology`].
#[derive(Default)]
pub struct BufferCache(Mutex<Vec<(CubeDevice, Arc<Buffers>)>>);

impl std::fmt::Debug for BufferCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let devices = self.0.lock().map(|c| c.len()).unwrap_or(0);
        write!(f, "BufferCache({devices} devices)")
    }
}

impl Buffers {
    fn upload(ctx: &Ctx, tab: &GpuTables) -> Self {
        let u = |v: &[u32]| ctx.client.create_from_slice(u32::as_bytes(&nonempty(v, 0)));
        let fl = |v: &[f32]| {
            ctx.client
                .create_from_slice(f32::as_bytes(&nonempty(v, 0.0)))
        };
        let csr = |c: &Csr| CsrBuf {
            offsets: u(&c.offsets),
            entries: u(&c.entries),
            weights: fl(&c.weights),
            targets: c.offsets.len() - 1,
            len: c.entries.len(),
        };
        Buffers {
            texel_from_samples: csr(&tab.texel_from_samples),
            face_from_texels: csr(&tab.face_from_texels),
            face_from_samples: csr(&tab.face_from_samples),
            vertex_from_texels: csr(&tab.vertex_from_texels),
            vertex_from_samples: csr(&tab.vertex_from_samples),
            vertex_from_corners: csr(&tab.vertex_from_corners),
            faces: u(&tab.faces),
            texel_frame: u(&tab.texel_frame),
            texel_corners: u(&tab.texel_corners),
            texel_bary: fl(&tab.texel_bary),
            taps: u(&tab.taps),
            tap_weights: fl(&tab.tap_weights),
            sample_frame: u(&tab.sample_frame),
            sample_corners: u(&tab.sample_corners),
            sample_bary: fl(&tab.sample_bary),
        }
    }
}

struct Lifter<'a> {
    ctx: Ctx,
    params: &'a LiftParams,
    rr: usize,
    n: usize,
    f: usize,
    v: usize,
    scaled: bool,
    b: Arc<Buffers>,
}

impl<'a> Lifter<'a> {
    fn new(reference: &CubeTensor, params: &'a LiftParams) -> Self {
        let ctx = Ctx::new(reference);
        let t = &params.topology;
        let b = {
            let mut cache = t.gpu_cache.0.lock().unwrap_or_else(|e| e.into_inner());
            match cache.iter().find(|(d, _)| *d == ctx.device) {
                Some((_, b)) => b.clone(),
                None => {
                    let b = Arc::new(Buffers::upload(&ctx, t.gpu_tables()));
                    cache.push((ctx.device.clone(), b.clone()));
                    b
                }
            }
        };
        Lifter {
            rr: t.res() * t.res(),
            n: t.len(),
            f: t.faces.len(),
            v: t.num_vertices,
            scaled: params.frame == FrameKind::ScaledRotation,
            ctx,
            params,
            b,
        }
    }

    fn frames(&self, vertices: &Handle) -> Handle {
        let out = self.ctx.empty(self.f * 9);
        let (count, dim) = self.ctx.elementwise(self.f);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the face count.
        unsafe {
            face_frames::launch_unchecked(
                &self.ctx.client,
                count,
                dim,
                arg(vertices, self.v * 3),
                arg(&self.b.faces, self.f * 3),
                arg(&out, self.f * 9),
                self.f as u32,
                self.scaled,
            );
        }
        out
    }

    /// Per-row lift of `rows` rows.
    #[allow(clippy::too_many_arguments)]
    fn lift_rows(
        &self,
        local: &Handle,
        local_len: usize,
        strides: (u32, u32),
        frames: &Handle,
        vertices: &Handle,
        rows: usize,
        global: bool,
    ) -> Handle {
        let out = self.ctx.empty(rows * OUT_CHANNELS);
        let (fr, co, ba) = if global {
            (
                &self.b.texel_frame,
                &self.b.texel_corners,
                &self.b.texel_bary,
            )
        } else {
            (
                &self.b.sample_frame,
                &self.b.sample_corners,
                &self.b.sample_bary,
            )
        };
        let (count, dim) = self.ctx.elementwise(rows);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the row count.
        unsafe {
            lift_rows::launch_unchecked(
                &self.ctx.client,
                count,
                dim,
                arg(local, local_len),
                strides.0,
                strides.1,
                arg(frames, self.f * 9),
                arg(fr, rows),
                arg(vertices, self.v * 3),
                arg(co, rows * 3),
                arg(ba, rows * 3),
                arg(&out, rows * OUT_CHANNELS),
                rows as u32,
                !global,
            );
        }
        out
    }

    /// Blend of a per-texel source with `channels` channels at the samples.
    fn blend(&self, src: &Handle, strides: (u32, u32), channels: usize, sigmoid: bool) -> Handle {
        let out = self.ctx.empty(self.n * channels);
        let (count, dim) = self.ctx.elementwise(self.n);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the sample count.
        unsafe {
            blend::launch_unchecked(
                &self.ctx.client,
                count,
                dim,
                arg(src, self.rr * channels),
                strides.0,
                strides.1,
                arg(&self.b.taps, self.n * 4),
                arg(&self.b.tap_weights, self.n * 4),
                arg(&out, self.n * channels),
                self.n as u32,
                channels as u32,
                sigmoid,
            );
        }
        out
    }

    /// `out[t * out_row + c * out_ch] (+)= sum_e w_e values[entries_e * val_row + off + c]`.
    #[allow(clippy::too_many_arguments)]
    fn gather(
        &self,
        csr: &CsrBuf,
        values: &Handle,
        values_len: usize,
        (val_row, val_offset): (u32, u32),
        out: &Handle,
        out_len: usize,
        (out_row, out_ch): (u32, u32),
        channels: usize,
        accumulate: bool,
    ) {
        let targets = csr.targets;
        let c = &self.ctx.client;
        let (count, dim) = self.ctx.elementwise(targets);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the target count and
        // reads entries only within `offsets`.
        unsafe {
            csr_gather::launch_unchecked(
                c,
                count,
                dim,
                arg(values, values_len),
                val_row,
                val_offset,
                arg(&csr.offsets, targets + 1),
                arg(&csr.entries, csr.len),
                arg(&csr.weights, csr.len),
                arg(out, out_len),
                out_row,
                out_ch,
                targets as u32,
                channels as u32,
                accumulate,
            );
        }
    }

    fn forward(&self, local: &Handle, vertices: &Handle) -> Handle {
        let frames = self.frames(vertices);
        let lc = LOCAL_CHANNELS;
        let channel_major = (1u32, self.rr as u32);
        match self.params.mode {
            LiftMode::Global => {
                let payload = self.lift_rows(
                    local,
                    lc * self.rr,
                    channel_major,
                    &frames,
                    vertices,
                    self.rr,
                    true,
                );
                self.blend(&payload, (OUT_CHANNELS as u32, 1), OUT_CHANNELS, true)
            }
            LiftMode::Local => {
                let sampled = self.blend(local, channel_major, lc, false);
                self.lift_rows(
                    &sampled,
                    lc * self.n,
                    (lc as u32, 1),
                    &frames,
                    vertices,
                    self.n,
                    false,
                )
            }
        }
    }

    /// Per-row lift backward: returns (per-row frame gradients [rows, 9]).
    #[allow(clippy::too_many_arguments)]
    fn lift_rows_backward(
        &self,
        local: &Handle,
        local_len: usize,
        strides: (u32, u32),
        frames: &Handle,
        dout: &Handle,
        dlocal: &Handle,
        dl_strides: (u32, u32),
        rows: usize,
        global: bool,
    ) -> Handle {
        let dframes = self.ctx.empty(rows * 9);
        let fr = if global {
            &self.b.texel_frame
        } else {
            &self.b.sample_frame
        };
        let (count, dim) = self.ctx.elementwise(rows);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the row count.
        unsafe {
            lift_rows_backward::launch_unchecked(
                &self.ctx.client,
                count,
                dim,
                arg(local, local_len),
                strides.0,
                strides.1,
                arg(frames, self.f * 9),
                arg(fr, rows),
                arg(dout, rows * OUT_CHANNELS),
                arg(dlocal, rows * LOCAL_CHANNELS),
                dl_strides.0,
                dl_strides.1,
                arg(&dframes, rows * 9),
                rows as u32,
                !global,
            );
        }
        dframes
    }

    fn backward(&self, local: &Handle, vertices: &Handle, dout: &Handle) -> (Handle, Handle) {
        let frames = self.frames(vertices);
        let lc = LOCAL_CHANNELS;
        let oc = OUT_CHANNELS;
        let channel_major = (1u32, self.rr as u32);
        let dlocal = self.ctx.empty(lc * self.rr);
        let dface = self.ctx.empty(self.f * 9);
        let dverts = self.ctx.empty(self.v * 3);
        match self.params.mode {
            LiftMode::Global => {
                let payload = self.lift_rows(
                    local,
                    lc * self.rr,
                    channel_major,
                    &frames,
                    vertices,
                    self.rr,
                    true,
                );
                let logits = self.blend(&payload, (oc as u32, 1), oc, false);
                let d = self.ctx.empty(self.n * oc);
                let (count, dim) = self.ctx.elementwise(self.n);
                // SAFETY: buffer lengths as passed; the kernel bounds-checks the count.
                unsafe {
                    opacity_grad::launch_unchecked(
                        &self.ctx.client,
                        count,
                        dim,
                        arg(dout, self.n * oc),
                        arg(&logits, self.n * oc),
                        arg(&d, self.n * oc),
                        self.n as u32,
                    );
                }
                let dpay = self.ctx.empty(self.rr * oc);
                self.gather(
                    &self.b.texel_from_samples,
                    &d,
                    self.n * oc,
                    (oc as u32, 0),
                    &dpay,
                    self.rr * oc,
                    (oc as u32, 1),
                    oc,
                    false,
                );
                let dtex_frames = self.lift_rows_backward(
                    local,
                    lc * self.rr,
                    channel_major,
                    &frames,
                    &dpay,
                    &dlocal,
                    channel_major,
                    self.rr,
                    true,
                );
                self.gather(
                    &self.b.face_from_texels,
                    &dtex_frames,
                    self.rr * 9,
                    (9, 0),
                    &dface,
                    self.f * 9,
                    (9, 1),
                    9,
                    false,
                );
                self.gather(
                    &self.b.vertex_from_texels,
                    &dpay,
                    self.rr * oc,
                    (oc as u32, 0),
                    &dverts,
                    self.v * 3,
                    (3, 1),
                    3,
                    false,
                );
            }
            LiftMode::Local => {
                let sampled = self.blend(local, channel_major, lc, false);
                let dl = self.ctx.empty(self.n * lc);
                let dsample_frames = self.lift_rows_backward(
                    &sampled,
                    lc * self.n,
                    (lc as u32, 1),
                    &frames,
                    dout,
                    &dl,
                    (lc as u32, 1),
                    self.n,
                    false,
                );
                self.gather(
                    &self.b.texel_from_samples,
                    &dl,
                    self.n * lc,
                    (lc as u32, 0),
                    &dlocal,
                    lc * self.rr,
                    channel_major,
                    lc,
                    false,
                );
                self.gather(
                    &self.b.face_from_samples,
                    &dsample_frames,
                    self.n * 9,
                    (9, 0),
                    &dface,
                    self.f * 9,
                    (9, 1),
                    9,
                    false,
                );
                self.gather(
                    &self.b.vertex_from_samples,
                    dout,
                    self.n * oc,
                    (oc as u32, 0),
                    &dverts,
                    self.v * 3,
                    (3, 1),
                    3,
                    false,
                );
            }
        }
        let dcorners = self.ctx.empty(self.f * 9);
        let (count, dim) = self.ctx.elementwise(self.f);
        // SAFETY: buffer lengths as passed; the kernel bounds-checks the face count.
        unsafe {
            face_frames_backward::launch_unchecked(
                &self.ctx.client,
                count,
                dim,
                arg(vertices, self.v * 3),
                arg(&self.b.faces, self.f * 3),
                arg(&dface, self.f * 9),
                arg(&dcorners, self.f * 9),
                self.f as u32,
                self.scaled,
            );
        }
        self.gather(
            &self.b.vertex_from_corners,
            &dcorners,
            self.f * 9,
            (3, 0),
            &dverts,
            self.v * 3,
            (3, 1),
            3,
            true,
        );
        (dlocal, dverts)
    }
}

/// `v`, or a one-element buffer holding `fill` when `v` is empty (buffers cannot be empty).
fn nonempty<T: Copy>(v: &[T], fill: T) -> Vec<T> {
    if v.is_empty() { vec![fill] } else { v.to_vec() }
}

/// Forward on the GPU: local maps `[14, R, R]`, vertices `[V, 3]` → packed `[N, 13]`.
pub fn forward(local: CubeTensor, vertices: CubeTensor, params: &LiftParams) -> CubeTensor {
    let l = Lifter::new(&local, params);
    let local = l.ctx.float_input(local);
    let vertices = l.ctx.float_input(vertices);
    let out = l.forward(&local.handle, &vertices.handle);
    l.ctx.tensor(out, [l.n, OUT_CHANNELS], DType::F32)
}

/// Backward on the GPU: `grad_out` `[N, 13]` → (d local `[14, R, R]`, d vertices `[V, 3]`).
pub fn backward(
    local: CubeTensor,
    vertices: CubeTensor,
    grad_out: CubeTensor,
    params: &LiftParams,
) -> (CubeTensor, CubeTensor) {
    let l = Lifter::new(&local, params);
    let local = l.ctx.float_input(local);
    let vertices = l.ctx.float_input(vertices);
    let grad_out = l.ctx.float_input(grad_out);
    let r = params.topology.res();
    let (dl, dv) = l.backward(&local.handle, &vertices.handle, &grad_out.handle);
    (
        l.ctx.tensor(dl, [LOCAL_CHANNELS, r, r], DType::F32),
        l.ctx.tensor(dv, [l.v, 3], DType::F32),
    )
}
