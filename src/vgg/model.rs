//! The burn-onnx generated VGG16 feature stack (see build.rs and models/).
#![allow(clippy::all, unused)]
include!(concat!(env!("OUT_DIR"), "/model/vgg16_features.rs"));
