//! The two halves every op's `Autodiff` implementation shares: recording the forward pass in
//! burn's graph ([`forward`]) and handing the parents their gradients in the backward pass
//! ([`backward`], declared with [`backward_op!`](crate::backward_op)). Each op keeps only what is its own: which tensors are its parents, what
//! it saves, and which of its backend's functions computes the gradients.

use burn::backend::Backend;
use burn::backend::autodiff::{
    Autodiff,
    checkpoint::strategy::CheckpointStrategy,
    grads::Gradients,
    ops::{Backward, NodeGuard, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;

/// Runs an op's forward pass on the inner backend and records it in the graph with `op` as
/// its backward step and `nodes` as its parents. `run` computes the output from the inner
/// inputs; when a parent is tracked, `keep` builds the state the backward step reads from
/// those inputs and the output (so an input is moved, not copied, into the state).
pub fn forward<B, C, Op, I, const N: usize>(
    op: Op,
    nodes: [NodeGuard; N],
    inner: I,
    run: impl FnOnce(I) -> FloatTensor<B>,
    keep: impl FnOnce(I, &FloatTensor<B>) -> Op::State,
) -> FloatTensor<Autodiff<B, C>>
where
    B: Backend,
    C: CheckpointStrategy,
    Op: Backward<B, N>,
    I: Clone,
{
    let keep = |i, out: FloatTensor<B>| (keep(i, &out), out);
    forward_with::<B, C, Op, I, FloatTensor<B>, N>(op, nodes, inner, run, keep, |out| out)
}

/// [`forward`] for an op whose forward pass yields more than its output (`R`, e.g. a
/// renderer's intermediate buffers): `keep` splits it into the backward step's state and the
/// output when a parent is tracked, `output` takes the output alone otherwise.
pub fn forward_with<B, C, Op, I, R, const N: usize>(
    op: Op,
    nodes: [NodeGuard; N],
    inner: I,
    run: impl FnOnce(I) -> R,
    keep: impl FnOnce(I, R) -> (Op::State, FloatTensor<B>),
    output: impl FnOnce(R) -> FloatTensor<B>,
) -> FloatTensor<Autodiff<B, C>>
where
    B: Backend,
    C: CheckpointStrategy,
    Op: Backward<B, N>,
    I: Clone,
{
    match op.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let (state, out) = keep(inner.clone(), run(inner));
            prep.finish(state, out)
        }
        OpsKind::UnTracked(prep) => prep.finish(output(run(inner))),
    }
}

/// An op's backward step: consumes the gradient of its output, computes the gradients of its
/// `N` parents with `grads_of` (from the saved state and that gradient, in the parents'
/// order) and registers each one whose parent is tracked.
pub fn backward<B: Backend, S, const N: usize>(
    ops: Ops<S, N>,
    grads: &mut Gradients,
    grads_of: impl FnOnce(S, FloatTensor<B>) -> [FloatTensor<B>; N],
) {
    let grad = grads.consume::<B>(&ops.node);
    let values = grads_of(ops.state, grad);
    for (node, value) in ops.parents.into_iter().zip(values) {
        if let Some(node) = node {
            grads.register::<B>(node.id, value);
        }
    }
}

/// Declares an op's backward step: the unit struct `$op`, and its `Backward<B, N>` for
/// every backend `B` with the extension `$ext`, whose state is `$state` and whose parents'
/// gradients `$grads` computes from the state and the output's gradient (a closure, as
/// [`backward`] takes it; `B` is the backend).
#[macro_export]
macro_rules! backward_op {
    ($(#[$doc:meta])* $op:ident<$n:literal>: $ext:path, $state:ty, $grads:expr) => {
        $(#[$doc])*
        #[derive(Debug)]
        struct $op;

        impl<B: ::burn::backend::Backend + $ext> ::burn::backend::autodiff::ops::Backward<B, $n>
            for $op
        {
            type State = $state;

            fn backward(
                self,
                ops: ::burn::backend::autodiff::ops::Ops<Self::State, $n>,
                grads: &mut ::burn::backend::autodiff::grads::Gradients,
                _: &mut ::burn::backend::autodiff::checkpoint::base::Checkpointer,
            ) {
                $crate::autodiff::backward::<B, _, $n>(ops, grads, $grads);
            }
        }
    };
}
