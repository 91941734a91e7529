//! The job the speed figures are measured on (docs/performance.md): the paper's board
//! (12 targets) rendered by the simulator at 1280x720, 20 frames 50 µm apart, as a
//! `rigctl process` folder (frames/*.png + steps.csv).

use rigd::sim::render::{render_frame, View as CamView};
use rigd::sim::{Board, CameraModel};

pub const STEP_UM: f64 = 50.0;

/// The first `n` frames of the scan.
pub fn frames(n: usize) -> Vec<image::RgbImage> {
    let board = Board::paper();
    let cam = CameraModel::default();
    (0..n)
        .map(|i| {
            let view = CamView::at([237.0 + STEP_UM * i as f64, 411.0]);
            render_frame(&board, &cam, &view, 1.0, 100 + i as u64)
        })
        .collect()
}

/// The 20-frame folder, written into `dir`: each frame as the daemon records it (its PNG
/// settings and metadata chunks: `frame_png`).
pub fn write_folder(dir: &std::path::Path) {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    let mut steps = String::from("index,position_um\n");
    let scale_um_per_px = CameraModel::default().scale_um_per_px;
    for (i, f) in frames(20).iter().enumerate() {
        let text = vec![("index".to_string(), i.to_string())];
        let png = rigd::session::frame_png::encode(f, scale_um_per_px, text).unwrap();
        std::fs::write(dir.join(format!("frames/{i:04}.png")), png).unwrap();
        steps.push_str(&format!("{i},{}\n", STEP_UM * i as f64));
    }
    std::fs::write(dir.join("steps.csv"), steps).unwrap();
}
