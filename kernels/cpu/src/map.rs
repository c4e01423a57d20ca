//! A channels-last feature map, the layout of [`crate::conv3x3`], [`crate::winograd`] and
//! [`crate::pool`].

/// A channels-last map: `data[(y·w + x)·c + channel]`.
#[derive(Clone, Debug)]
pub struct Map {
    pub data: Vec<f32>,
    pub h: usize,
    pub w: usize,
}
