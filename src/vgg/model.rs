//! The VGG16 feature stack burn-onnx generates from
//! `models/vgg16_features.onnx` (`LoadStrategy::None`: the weights come from
//! `vgg::weights`), committed as `models/vgg16_features.rs`;
//! tests/vgg.rs (model_is_burn_onnx_import_of_the_onnx_file) regenerates it and compares.
// Generated code: no lint of ours applies (too_many_lines is a pedantic lint, outside clippy::all).
#![allow(clippy::all, clippy::pedantic, unused)]
include!(concat!(env!("CARGO_MANIFEST_DIR"), "/models/vgg16_features.rs"));

/// The imported graph's pieces, in network order, for a forward pass that
/// runs the same modules layer by layer (`crate::vgg::staged`).
impl Model {
    /// The input scaling (x 255) and the Caffe mean subtracted after it.
    pub(crate) fn input_constants(&self) -> (Tensor<1>, Tensor<4>) {
        (self.constant1.val(), self.constant2.val())
    }

    /// The 13 convolutions.
    pub(crate) fn convs(&self) -> [&Conv2d; 13] {
        [
            &self.conv2d1,
            &self.conv2d2,
            &self.conv2d3,
            &self.conv2d4,
            &self.conv2d5,
            &self.conv2d6,
            &self.conv2d7,
            &self.conv2d8,
            &self.conv2d9,
            &self.conv2d10,
            &self.conv2d11,
            &self.conv2d12,
            &self.conv2d13,
        ]
    }

    /// The 4 max-pools (after relu1_2, relu2_2, relu3_3, relu4_3).
    pub(crate) fn pools(&self) -> [&MaxPool2d; 4] {
        [&self.maxpool2d1, &self.maxpool2d2, &self.maxpool2d3, &self.maxpool2d4]
    }
}

impl Model {
    /// The same graph carrying other weights: the 13 convolutions' (weight
    /// `[out, in, 3, 3]`, bias `[out]`) in network order, the input scale
    /// (`[1]`) and the mean subtracted after it (`[1, 3, 1, 1]`).
    pub(crate) fn with_weights(
        mut self,
        convs: Vec<(Tensor<4>, Tensor<1>)>,
        scale: Tensor<1>,
        mean: Tensor<4>,
    ) -> Self {
        assert_eq!(convs.len(), 13, "VGG16 has 13 convolutions");
        let slots = [
            &mut self.conv2d1,
            &mut self.conv2d2,
            &mut self.conv2d3,
            &mut self.conv2d4,
            &mut self.conv2d5,
            &mut self.conv2d6,
            &mut self.conv2d7,
            &mut self.conv2d8,
            &mut self.conv2d9,
            &mut self.conv2d10,
            &mut self.conv2d11,
            &mut self.conv2d12,
            &mut self.conv2d13,
        ];
        for (conv, (weight, bias)) in slots.into_iter().zip(convs) {
            assert_eq!(conv.weight.dims(), weight.dims(), "a VGG16 convolution's weight shape");
            conv.weight = burn::module::Param::from_tensor(weight);
            conv.bias = Some(burn::module::Param::from_tensor(bias));
        }
        self.constant1 = burn::module::Param::from_tensor(scale);
        self.constant2 = burn::module::Param::from_tensor(mean);
        self
    }
}
