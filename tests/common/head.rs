//! The tiny hand-made head model shared by the head-model and dataset tests.

use texavatars::head::model::HeadModel;

/// Six vertices, five joints. Joint i sits at vertex i (identity regressor on the first
/// five); vertex i is skinned to joint i, and vertex 5 (one unit above the jaw joint) to
/// the jaw. One shape direction (vertex 0 +x), `num_expr` (1 to 3) expression directions
/// (vertex 5 +z, vertex 5 +x, vertex 4 +y), and one pose corrective (vertex 5's y moves
/// with the jaw's `(R - I)[1][1]`).
pub fn tiny_head(num_expr: usize) -> HeadModel {
    assert!((1..=3).contains(&num_expr), "1 to 3 expression directions");
    let v_template = vec![
        [0.0, 0.0, 0.0],  // root
        [0.0, 1.0, 0.0],  // neck
        [0.0, 2.0, 0.0],  // jaw
        [-1.0, 3.0, 0.0], // left eye
        [1.0, 3.0, 0.0],  // right eye
        [0.0, 3.0, 0.0],  // on the jaw
    ];
    let v = v_template.len();
    let k = 1 + num_expr;
    let mut shapedirs = vec![0.0f32; v * 3 * k];
    shapedirs[0] = 1.0; // shape: vertex 0 +x
    let expr = [(5, 2), (5, 0), (4, 1)]; // (vertex, axis) of each expression direction
    for (e, &(vertex, axis)) in expr.iter().take(num_expr).enumerate() {
        shapedirs[(vertex * 3 + axis) * k + 1 + e] = 1.0;
    }
    let p = 36;
    let mut posedirs = vec![0.0f32; v * 3 * p];
    posedirs[(5 * 3 + 1) * p + 9 + 4] = 1.0;
    let mut j_regressor = vec![0.0f32; 5 * v];
    let mut weights = vec![0.0f32; v * 5];
    for i in 0..5 {
        j_regressor[i * v + i] = 1.0;
        weights[i * 5 + i] = 1.0;
    }
    weights[5 * 5 + 2] = 1.0;
    HeadModel {
        v_template,
        shapedirs,
        num_shape: 1,
        num_expr,
        posedirs,
        j_regressor,
        weights,
        parents: vec![None, Some(0), Some(1), Some(1), Some(1)],
        faces: vec![[0, 1, 2], [2, 5, 3], [2, 5, 4]],
    }
}
