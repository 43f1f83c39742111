//! `kernels::conv3x3`'s kernel as a Burn operation with its own backward, for
//! the CPU backends (flex, ndarray) and autodiff over them.
//!
//! Burn 0.22 picks the backend at run time (`Dispatch`); an operation of
//! our own is a backend extension trait that the `backend_extension` macro
//! routes to the backend a tensor lives on. The CPU backends implement it
//! on host memory (`kernels::conv3x3`), `Autodiff<B>` records a backward step
//! whose gradients are the kernel's. On wgpu [`conv3x3`] is Burn's own
//! `conv2d` (the GPU has its own convolution kernels), and so are convolutions
//! other than 3x3 / stride 1 / padding 1.

// NdArray is deprecated upstream and stays a supported backend here; the
// code the extension macro generates names it too.
#![allow(deprecated)]

use std::sync::{Arc, OnceLock};

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::Tensor;

use crate::kernels::conv3x3::PreparedWeights;

#[cfg(any(feature = "flex", feature = "ndarray"))]
use crate::util::tensor::is_host_memory;

/// The operation itself: only builds with a CPU backend need it.
#[cfg(any(feature = "flex", feature = "ndarray"))]
mod host_op {
    #[cfg(feature = "flex")]
    use burn::backend::Flex;
    #[cfg(feature = "ndarray")]
    use burn::backend::NdArray;
    use burn::backend::TensorMetadata;
    use burn::backend::autodiff::Autodiff;
    use burn::backend::autodiff::checkpoint::base::Checkpointer;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::autodiff::grads::Gradients;
    use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
    use burn::backend::tensor::FloatTensor;
    use burn::backend::{Backend, backend_extension};
    use burn::tensor::TensorData;

    use std::sync::Arc;

    use crate::kernels::conv3x3::{self as kernel, Dims, PreparedWeights, WinogradWeights};

    /// A 3x3 convolution, stride 1, zero padding 1, with bias, and optionally
    /// the ReLU after it (VGG's pairs: one pass over the output instead of two,
    /// and no pre-activation tensor kept for the backward).
    #[cfg_attr(all(feature = "flex", feature = "ndarray"), backend_extension(Flex, NdArray, Autodiff))]
    #[cfg_attr(all(feature = "flex", not(feature = "ndarray")), backend_extension(Flex, Autodiff))]
    #[cfg_attr(all(not(feature = "flex"), feature = "ndarray"), backend_extension(NdArray, Autodiff))]
    pub trait Conv3x3Backend: Backend {
        /// `x` `[N, C, H, W]`, `weight` `[K, C, 3, 3]`, `bias` `[K]` -> `[N, K, H, W]`.
        fn conv3x3(
            x: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            bias: FloatTensor<Self>,
            relu: bool,
        ) -> FloatTensor<Self>;

        /// As [`conv3x3`](Self::conv3x3) with weights prepared once
        /// (`PreparedWeights`: a frozen layer's), and no weight gradient.
        fn conv3x3_prepared(
            x: FloatTensor<Self>,
            bias: FloatTensor<Self>,
            weights: Arc<PreparedWeights>,
            relu: bool,
        ) -> FloatTensor<Self>;
    }

    /// The two CPU backends run the operation alike, on host memory.
    macro_rules! host_backend {
        ($backend:ty) => {
            impl Conv3x3Backend for $backend {
                fn conv3x3(
                    x: FloatTensor<Self>,
                    weight: FloatTensor<Self>,
                    bias: FloatTensor<Self>,
                    relu: bool,
                ) -> FloatTensor<Self> {
                    host_forward::<Self>(x, weight, bias, relu)
                }

                fn conv3x3_prepared(
                    x: FloatTensor<Self>,
                    bias: FloatTensor<Self>,
                    weights: Arc<PreparedWeights>,
                    relu: bool,
                ) -> FloatTensor<Self> {
                    host_forward_prepared::<Self>(x, bias, &weights, relu)
                }
            }
        };
    }

    #[cfg(feature = "flex")]
    host_backend!(Flex);
    #[cfg(feature = "ndarray")]
    host_backend!(NdArray);

    /// The backward step: the kernel's input, weight and bias gradients.
    #[derive(Debug)]
    struct Conv3x3Backward;

    impl<B: Backend> Backward<B, 3> for Conv3x3Backward {
        /// The forward's input and weights, and its output when it ends in a
        /// ReLU.
        type State = (FloatTensor<B>, FloatTensor<B>, Option<FloatTensor<B>>);

        fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_x, node_weight, node_bias] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            let (x, weight, relu_output) = ops.state;
            let device = grad.device();
            let (dy, dy_dims) = output_grad::<B>(grad, relu_output);
            if let Some(node) = node_x {
                let (w, w_dims) = to_host::<B>(weight);
                let flipped = WinogradWeights::flipped_transposed(&w, w_dims[0], w_dims[1]);
                let dx = kernel::input_grad(&dy, dims(&dy_dims), &flipped);
                let x_dims = [dy_dims[0], w_dims[1], dy_dims[2], dy_dims[3]];
                grads.register::<B>(node.id, from_host::<B>(dx, x_dims.to_vec(), &device));
            }
            if let Some(node) = node_weight {
                let (xs, x_dims) = to_host::<B>(x);
                let k = dy_dims[1];
                let dw = kernel::weight_grad(&xs, dims(&x_dims), &dy, k);
                grads.register::<B>(node.id, from_host::<B>(dw, vec![k, x_dims[1], 3, 3], &device));
            }
            if let Some(node) = node_bias {
                let db = kernel::bias_grad(&dy, dims(&dy_dims));
                grads.register::<B>(node.id, from_host::<B>(db, vec![dy_dims[1]], &device));
            }
        }
    }

    /// The output's gradient as host values and its shape, through the
    /// ReLU when the forward ended in one (its output given): no gradient
    /// where the output was clamped (relu'(0) = 0, as Burn's relu).
    fn output_grad<B: Backend>(grad: FloatTensor<B>, relu_output: Option<FloatTensor<B>>) -> (Vec<f32>, Vec<usize>) {
        let (mut dy, dy_dims) = to_host::<B>(grad);
        if let Some(y) = relu_output {
            let (y, _) = to_host::<B>(y);
            for (d, &y) in dy.iter_mut().zip(&y) {
                if y <= 0.0 {
                    *d = 0.0;
                }
            }
        }
        (dy, dy_dims)
    }

    /// The backward step of the prepared operation: the input and bias
    /// gradients (the weights are frozen).
    #[derive(Debug)]
    struct PreparedBackward {
        weights: Arc<PreparedWeights>,
    }

    impl<B: Backend> Backward<B, 2> for PreparedBackward {
        /// The forward's output when it ends in a ReLU.
        type State = Option<FloatTensor<B>>;

        fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_x, node_bias] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            let device = grad.device();
            let (dy, dy_dims) = output_grad::<B>(grad, ops.state);
            if let Some(node) = node_x {
                let flipped = self.weights.flipped();
                let dx = kernel::input_grad(&dy, dims(&dy_dims), flipped);
                let x_dims = [dy_dims[0], flipped.out_channels(), dy_dims[2], dy_dims[3]];
                grads.register::<B>(node.id, from_host::<B>(dx, x_dims.to_vec(), &device));
            }
            if let Some(node) = node_bias {
                let db = kernel::bias_grad(&dy, dims(&dy_dims));
                grads.register::<B>(node.id, from_host::<B>(db, vec![dy_dims[1]], &device));
            }
        }
    }

    impl<B: Conv3x3Backend, C: CheckpointStrategy> Conv3x3Backend for Autodiff<B, C> {
        fn conv3x3(
            x: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            bias: FloatTensor<Self>,
            relu: bool,
        ) -> FloatTensor<Self> {
            match Conv3x3Backward.prepare::<C>([x.node(), weight.node(), bias.node()]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    let (x, weight) = (x.into_primitive(), weight.into_primitive());
                    let output = B::conv3x3(x.clone(), weight.clone(), bias.into_primitive(), relu);
                    let relu_output = relu.then(|| output.clone());
                    prep.finish((x, weight, relu_output), output)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(B::conv3x3(x.into_primitive(), weight.into_primitive(), bias.into_primitive(), relu))
                }
            }
        }

        fn conv3x3_prepared(
            x: FloatTensor<Self>,
            bias: FloatTensor<Self>,
            weights: Arc<PreparedWeights>,
            relu: bool,
        ) -> FloatTensor<Self> {
            let backward = PreparedBackward { weights: weights.clone() };
            match backward.prepare::<C>([x.node(), bias.node()]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    let output = B::conv3x3_prepared(x.into_primitive(), bias.into_primitive(), weights, relu);
                    let relu_output = relu.then(|| output.clone());
                    prep.finish(relu_output, output)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(B::conv3x3_prepared(x.into_primitive(), bias.into_primitive(), weights, relu))
                }
            }
        }
    }

    /// The forward on host memory, for any backend whose tensors can be read.
    fn host_forward<B: Backend>(
        x: FloatTensor<B>,
        weight: FloatTensor<B>,
        bias: FloatTensor<B>,
        relu: bool,
    ) -> FloatTensor<B> {
        let (w, w_dims) = to_host::<B>(weight);
        assert!(w_dims.len() == 4 && w_dims[2..] == [3, 3], "conv3x3 weights [K, C, 3, 3], got {w_dims:?}");
        host_forward_with::<B>(x, bias, &WinogradWeights::new(&w, w_dims[0], w_dims[1]), relu)
    }

    /// The prepared forward on host memory.
    fn host_forward_prepared<B: Backend>(
        x: FloatTensor<B>,
        bias: FloatTensor<B>,
        weights: &PreparedWeights,
        relu: bool,
    ) -> FloatTensor<B> {
        host_forward_with::<B>(x, bias, weights.forward(), relu)
    }

    /// The kernel's forward with weights already in the Winograd domain.
    fn host_forward_with<B: Backend>(
        x: FloatTensor<B>,
        bias: FloatTensor<B>,
        weights: &WinogradWeights,
        relu: bool,
    ) -> FloatTensor<B> {
        let device = x.device();
        let (xs, x_dims) = to_host::<B>(x);
        let (b, _) = to_host::<B>(bias);
        assert_eq!(x_dims.len(), 4, "conv3x3 takes [N, C, H, W] input, got {x_dims:?}");
        let (k, c) = (weights.out_channels(), weights.in_channels());
        assert_eq!(x_dims[1], c, "conv3x3 weights [{k}, {c}, 3, 3] for input {x_dims:?}");
        let y = kernel::forward(&xs, dims(&x_dims), weights, Some(&b), relu);
        from_host::<B>(y, vec![x_dims[0], k, x_dims[2], x_dims[3]], &device)
    }

    fn dims(shape: &[usize]) -> Dims {
        Dims { n: shape[0], c: shape[1], h: shape[2], w: shape[3] }
    }

    /// A CPU backend's tensor as f32 values and its shape.
    fn to_host<B: Backend>(tensor: FloatTensor<B>) -> (Vec<f32>, Vec<usize>) {
        let data = burn::tensor::read_sync(B::float_into_data(tensor)).expect("reading a CPU backend's tensor");
        let shape = data.shape().to_vec();
        let values = data.convert::<f32>().try_into_vec::<f32>().expect("f32 values after conversion");
        (values, shape)
    }

    fn from_host<B: Backend>(values: Vec<f32>, shape: Vec<usize>, device: &B::Device) -> FloatTensor<B> {
        B::float_from_data(TensorData::new(values, shape), device)
    }
}

#[cfg(any(feature = "flex", feature = "ndarray"))]
pub use host_op::Conv3x3Backend;

/// `relu(conv(x))`, through [`conv3x3`] where it applies (a 3x3, stride
/// 1, padding 1 convolution with bias), else through Burn's own `conv2d`.
/// With `prepared` (the slot of a frozen layer, whose weights never
/// change), the CPU backends prepare the kernel's weights on first use and
/// reuse them.
pub fn conv3x3_relu_forward(conv: &Conv2d, x: Tensor<4>, prepared: Option<&PreparedSlot>) -> Tensor<4> {
    let Some(bias) = conv.bias.as_ref().filter(|_| is_3x3_same(conv)) else {
        return burn::tensor::activation::relu(conv.forward(x));
    };
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if let (Some(slot), true) = (prepared, is_host_memory(&x.device())) {
        let weights = slot.get_or_init(|| Arc::new(prepare(conv.weight.val()))).clone();
        let out = <burn::backend::Dispatch as Conv3x3Backend>::conv3x3_prepared(
            x.into_dispatch(),
            bias.val().into_dispatch(),
            weights,
            true,
        );
        return Tensor::from_dispatch(out);
    }
    #[cfg(not(any(feature = "flex", feature = "ndarray")))]
    let _ = prepared;
    conv3x3(x, conv.weight.val(), bias.val(), true)
}

/// A frozen layer's prepared kernel weights, filled on first use.
pub type PreparedSlot = OnceLock<Arc<PreparedWeights>>;

/// The kernel's weights of `weight` `[K, C, 3, 3]`.
#[cfg(any(feature = "flex", feature = "ndarray"))]
fn prepare(weight: Tensor<4>) -> PreparedWeights {
    let [k, c, _, _] = weight.dims();
    PreparedWeights::new(crate::util::tensor::to_vec(weight), k, c)
}

/// A 3x3, stride 1, padding 1 convolution with bias, then a ReLU when
/// `relu`: the Winograd kernel on the CPU backends (and autodiff over
/// them), Burn's `conv2d` on wgpu.
pub fn conv3x3(x: Tensor<4>, weight: Tensor<4>, bias: Tensor<1>, relu: bool) -> Tensor<4> {
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&x.device()) {
        let out = <burn::backend::Dispatch as Conv3x3Backend>::conv3x3(
            x.into_dispatch(),
            weight.into_dispatch(),
            bias.into_dispatch(),
            relu,
        );
        return Tensor::from_dispatch(out);
    }
    let options = burn::tensor::ops::ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let y = burn::tensor::module::conv2d(x, weight, Some(bias), options);
    if relu { burn::tensor::activation::relu(y) } else { y }
}

fn is_3x3_same(conv: &Conv2d) -> bool {
    conv.kernel_size == [3, 3]
        && conv.stride == [1, 1]
        && conv.dilation == [1, 1]
        && conv.groups == 1
        && matches!(conv.padding, PaddingConfig2d::Explicit(1, 1, 1, 1))
}

/// Checked against the Burn graph and autodiff, on every backend the test
/// command runs (`cargo test --lib graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout, clippy::print_stderr)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use burn::tensor::Tensor;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use crate::test_support::{backend, max_rel_err, tol};
    use crate::util::tensor::{floats, to_vec};

    /// The 3x3 convolution operation (`kernels::conv_op`: the Winograd kernel on
    /// the CPU backends, Burn's `conv2d` on wgpu) against Burn's `conv2d`,
    /// without and with the fused ReLU: the output and the gradients of the
    /// input, the weights and the bias, to 1e-4 relative (1e-3 on wgpu), on a
    /// batch of two images with odd sides.
    #[test]
    fn conv3x3_op_and_its_gradients_match_burns_conv2d() {
        use burn::tensor::module::conv2d;
        use burn::tensor::ops::ConvOptions;
        let device = backend().autodiff_device();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut values = |shape: [usize; 4]| {
            let len = shape.iter().product();
            floats((0..len).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect(), shape, &device)
        };
        let (n, c, k, h, w) = (2, 5, 7, 13, 10);
        let x = values([n, c, h, w]);
        let weight = values([k, c, 3, 3]);
        let bias = values([1, 1, 1, k]).reshape([k]);
        let upstream = values([n, k, h, w]);
        let run = |ours: bool, relu: bool| {
            let (x, weight, bias) =
                (x.clone().require_grad(), weight.clone().require_grad(), bias.clone().require_grad());
            let y = if ours {
                crate::kernels::conv_op::conv3x3(x.clone(), weight.clone(), bias.clone(), relu)
            } else {
                let y =
                    conv2d(x.clone(), weight.clone(), Some(bias.clone()), ConvOptions::new([1, 1], [1, 1], [1, 1], 1));
                if relu { burn::tensor::activation::relu(y) } else { y }
            };
            // A loss whose output gradient is `upstream`, not uniform.
            let grads = (y.clone() * upstream.clone()).sum().backward();
            let grad_of = |t: &Tensor<4>| to_vec(t.grad(&grads).expect("gradient"));
            [to_vec(y), grad_of(&x), grad_of(&weight), to_vec(bias.grad(&grads).expect("bias gradient"))]
        };
        for relu in [false, true] {
            let (ours, burn) = (run(true, relu), run(false, relu));
            let names = ["output", "input gradient", "weight gradient", "bias gradient"];
            for (name, (a, b)) in names.iter().zip(ours.iter().zip(&burn)) {
                let err = max_rel_err(a, b);
                println!("relu {relu}, {name}: max rel err {err:.2e}");
                assert!(b.iter().any(|v| v.abs() > 0.0), "{name}: reference is zero");
                assert!(err <= tol(1e-4), "relu {relu}, {name}: max rel err {err:.2e}");
            }
        }
    }

    /// The prepared-weights path of a frozen layer (`conv3x3_relu_forward` with
    /// a slot: `Vgg16`'s) against Burn's `conv2d` + ReLU: the output, the input
    /// gradient and the bias gradient to 1e-4 relative (1e-3 on wgpu), on a
    /// batch of two images with odd sides; the slot is filled once on the CPU
    /// backends (wgpu runs Burn's convolution and leaves it empty), and a
    /// second call through the filled slot gives the same output.
    #[test]
    fn prepared_conv3x3_matches_burns_conv2d() {
        use crate::kernels::conv_op::{PreparedSlot, conv3x3_relu_forward};
        use burn::nn::PaddingConfig2d;
        use burn::nn::conv::Conv2dConfig;
        let device = backend().autodiff_device();
        device.seed(9);
        let (n, c, k, h, w) = (2, 6, 5, 11, 9);
        let conv = Conv2dConfig::new([c, k], [3, 3]).with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1)).init(&device);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut values = |shape: [usize; 4]| {
            let len = shape.iter().product();
            floats((0..len).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect(), shape, &device)
        };
        let x = values([n, c, h, w]);
        let upstream = values([n, k, h, w]);
        let slot = PreparedSlot::new();
        let run = |prepared: Option<&PreparedSlot>| {
            let x = x.clone().require_grad();
            let y = match prepared {
                Some(_) => conv3x3_relu_forward(&conv, x.clone(), prepared),
                None => burn::tensor::activation::relu(conv.forward(x.clone())),
            };
            let grads = (y.clone() * upstream.clone()).sum().backward();
            let bias = conv.bias.as_ref().expect("bias").val();
            [
                to_vec(y),
                to_vec(x.grad(&grads).expect("input gradient")),
                to_vec(bias.grad(&grads).expect("bias gradient")),
            ]
        };
        let (ours, burn) = (run(Some(&slot)), run(None));
        for (name, (a, b)) in ["output", "input gradient", "bias gradient"].iter().zip(ours.iter().zip(&burn)) {
            let err = max_rel_err(a, b);
            println!("{name}: max rel err {err:.2e}");
            assert!(b.iter().any(|v| v.abs() > 0.0), "{name}: reference is zero");
            assert!(err <= tol(1e-4), "{name}: max rel err {err:.2e}");
        }
        let host = crate::util::tensor::is_host_memory(&device);
        assert_eq!(slot.get().is_some(), host, "the slot is filled on the CPU backends only");
        assert_eq!(run(Some(&slot))[0], ours[0], "a second call through the filled slot");
    }
}
