//! Video source through ffmpeg (feature `video`). FFmpeg's image2 demuxer reads a
//! numbered PNG sequence as a video, so the test needs no encoder.
#![cfg(feature = "video")]

use aim_capture::source::FrameSource;
use aim_capture::source::RawImage;
use aim_capture::video::VideoSource;

#[test]
fn png_sequence_decodes_as_video_with_exact_pixels() {
    let dir = std::env::temp_dir().join(format!("aim-video-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for k in 0..5u8 {
        let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 3, y as u8 * 5, k * 40]));
        img.save(dir.join(format!("f_{k:03}.png"))).unwrap();
    }
    let mut src = VideoSource::open(&dir.join("f_%03d.png"), None).unwrap();
    let mut n = 0;
    let mut last_t = i64::MIN;
    while let Some(f) = src.next_frame() {
        let f = f.unwrap();
        let RawImage::Rgb(img) = &f.image else { panic!("expected RGB") };
        assert_eq!(img.dimensions(), (64, 48));
        assert_eq!(img.get_pixel(10, 7).0, [30, 35, n as u8 * 40]);
        assert!(f.timestamp_ns > last_t);
        last_t = f.timestamp_ns;
        n += 1;
    }
    assert_eq!(n, 5);
    assert!(VideoSource::open(&dir.join("missing.mp4"), None).is_err());
    let _ = std::fs::remove_dir_all(&dir);
}
