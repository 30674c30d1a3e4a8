//! `--plot` output: the SVG as drawn, or rasterised to PNG with resvg (text in the system's
//! fonts, found through fontdb) for viewers and reports that do not take SVG.

use resvg::{tiny_skia, usvg};

use super::stdio::OutputArg;
use super::CliError;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PlotFormat {
    Svg,
    Png,
}

impl PlotFormat {
    /// `given`, else by the file name (`.png` is PNG), else SVG (standard output included).
    fn choose(given: Option<Self>, target: &OutputArg) -> Self {
        given.unwrap_or_else(|| {
            let is_png = target
                .path()
                .and_then(|p| p.extension())
                .is_some_and(|e| e.eq_ignore_ascii_case("png"));
            if is_png {
                Self::Png
            } else {
                Self::Svg
            }
        })
    }
}

/// Writes `svg` to `--plot` in the chosen format.
pub fn write(target: &OutputArg, format: Option<PlotFormat>, svg: &str) -> Result<(), CliError> {
    let bytes = match PlotFormat::choose(format, target) {
        PlotFormat::Svg => svg.as_bytes().to_vec(),
        PlotFormat::Png => rasterise(svg)?,
    };
    target.write("--plot", &bytes)
}

/// The SVG as PNG bytes, one pixel per SVG unit.
pub fn rasterise(svg: &str) -> Result<Vec<u8>, CliError> {
    let failed = |reason: String| CliError::Argument {
        argument: "--plot".into(),
        reason: format!("cannot draw the PNG: {reason}"),
    };
    let mut options = usvg::Options::default();
    let fonts = options.fontdb_mut();
    fonts.load_system_fonts();
    // fontdb maps `sans-serif` to Arial, which Linux systems rarely have: use a sans face that is
    // installed (DejaVu Sans on Debian), so the labels are drawn rather than dropped.
    let sans = fonts
        .faces()
        .flat_map(|face| face.families.iter().map(|(name, _)| name.clone()))
        .find(|name| name.contains("Sans") && !name.contains("Mono"));
    if let Some(family) = sans {
        fonts.set_sans_serif_family(family);
    }
    let tree = usvg::Tree::from_str(svg, &options).map_err(|e| failed(e.to_string()))?;
    let size = tree.size().to_int_size();
    let mut pixmap = tiny_skia::Pixmap::new(size.width(), size.height())
        .ok_or_else(|| failed(format!("empty picture ({size:?})")))?;
    resvg::render(&tree, tiny_skia::Transform::default(), &mut pixmap.as_mut());
    pixmap.encode_png().map_err(|e| failed(e.to_string()))
}
