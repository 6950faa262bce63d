//! What a share link carries: the studio's view state, and its URL-hash form.
//!
//! Defined once, here, for the page (which owns the state, reads and writes `location.hash`) and the
//! worker (which draws it). A link is untrusted input: [`ViewState::from_hash`] never panics, bounds
//! every size before it allocates, accepts only `http:` / `https:` sources, ignores what it does not
//! know, and reports what it dropped so the page can say so.
//!
//! Format (parameters in any order, `&`-separated, values percent-encoded):
//! `#src=URL&src=URL&cam=tx,ty,tz,yaw,pitch,dist,fov&colour=log_std_combined&filter=log_std_combined&t=1.25&size=2&hide=0,2&bg=dark&nav=orbit`
//! `&budget=N` (points a COPC map loads at once) and `&draw=quads` (the instanced-quad draw instead of the
//! default compute rasteriser) are added when set.
//! `cam` angles are degrees (yaw from +x towards +y, pitch up from the horizon, vertical field of view),
//! `dist` metres from the orbit target; `t` is the threshold (log10 std, metres) — absent means the
//! default rule (Tukey's fence), as in the native `points_filtered.ply`.
//!
//! The access token of a `silvr serve` on the network travels in the page's query, never in the hash:
//! `http://host:port/?token=…#src=…`. The page keeps the query when it rewrites the hash, passes the
//! token to the worker (which sends it as [`TOKEN_HEADER`] to the page's own origin only), and leaves it
//! out of the share links it hands out ([`query_without_token`]).

use glam::{DVec3, Mat4};
use serde::{Deserialize, Serialize};
use silvr_core::viewer::{Frame, Raster};

/// Longest hash the parser reads (browsers cap URLs at 2 MB or less; a view needs far less).
pub const MAX_HASH_BYTES: usize = 32 * 1024;
/// Most sources (layers) a link may open.
pub const MAX_SOURCES: usize = 16;
/// Longest source URL.
pub const MAX_URL_BYTES: usize = 2048;
/// Longest access token read from a page's query.
pub const MAX_TOKEN_BYTES: usize = 256;
/// The query parameter of `silvr serve`'s access token.
pub const TOKEN_PARAM: &str = "token";
/// The request header the token travels in (`silvr serve` requires it for `/data/` off loopback).
pub const TOKEN_HEADER: &str = "X-Silvr-Token";
/// Point size range (pixels).
pub const POINT_SIZE: (f32, f32) = (1.0, 32.0);
/// The point budget a link or the page may set for a COPC map (points loaded at once): from a glance at a
/// map to what a large hardware GPU draws.
pub const BUDGET_RANGE: (u64, u64) = (10_000, 50_000_000);

/// The orbit camera: a target, a direction to the eye, a distance and a field of view.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub target: [f64; 3],
    /// Degrees, from +x towards +y.
    pub yaw: f64,
    /// Degrees above the horizon, in [-89, 89].
    pub pitch: f64,
    /// Metres from the target to the eye (> 0).
    pub distance: f64,
    /// Vertical field of view, degrees in [5, 120].
    pub fov: f64,
}

impl Camera {
    pub const DEFAULT_FOV: f64 = 60.0;

    /// A camera that frames the box `min`..`max` from the south-west, 30° up.
    pub fn fit(min: [f64; 3], max: [f64; 3]) -> Self {
        let (lo, hi) = (DVec3::from_array(min), DVec3::from_array(max));
        let radius = ((hi - lo).length() * 0.5).max(0.1);
        let fov = Self::DEFAULT_FOV;
        Self {
            target: ((lo + hi) * 0.5).to_array(),
            yaw: 225.0,
            pitch: 30.0,
            distance: radius / (0.5 * fov.to_radians()).tan() * 1.1,
            fov,
        }
    }

    /// Unit vector from the target to the eye.
    pub fn back(&self) -> DVec3 {
        let (y, p) = (self.yaw.to_radians(), self.pitch.to_radians());
        DVec3::new(p.cos() * y.cos(), p.cos() * y.sin(), p.sin())
    }

    pub fn eye(&self) -> DVec3 {
        DVec3::from_array(self.target) + self.back() * self.distance
    }

    /// Clip planes that keep a scene of `radius` around the target.
    pub fn clip(&self, radius: f64) -> (f64, f64) {
        let near = (self.distance * 1e-3).max(1e-3);
        (near, (self.distance + radius) * 4.0 + near * 10.0)
    }

    /// World (relative to `reference`) → clip space, for a `width` × `height` target.
    pub fn view_proj(&self, (width, height): (u32, u32), radius: f64, reference: DVec3) -> Mat4 {
        Frame::look_at(
            self.eye(),
            DVec3::from_array(self.target),
            self.fov.to_radians(),
            self.clip(radius),
            (width, height),
            reference,
        )
    }

    /// Keeps every field in its documented range (a link may say anything).
    pub fn clamped(mut self) -> Option<Self> {
        let finite = self.target.iter().all(|v| v.is_finite())
            && [self.yaw, self.pitch, self.distance, self.fov]
                .iter()
                .all(|v| v.is_finite());
        if !finite || self.target.iter().any(|v| v.abs() > 1e9) {
            return None;
        }
        self.yaw = self.yaw.rem_euclid(360.0);
        self.pitch = self.pitch.clamp(-89.0, 89.0);
        self.distance = self.distance.clamp(1e-3, 1e7);
        self.fov = self.fov.clamp(5.0, 120.0);
        Some(self)
    }
}

/// What points are coloured by.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Colour {
    Rgb,
    /// A scalar property of the cloud (`log_std_combined`, `log_std_colour`, `log_std_depth`, `error_m`).
    Field(String),
    /// Each layer in its own colour.
    Layer,
}

impl Colour {
    fn as_param(&self) -> &str {
        match self {
            Colour::Rgb => "rgb",
            Colour::Layer => "layer",
            Colour::Field(f) => f,
        }
    }

    fn from_param(s: &str) -> Option<Self> {
        match s {
            "rgb" => Some(Colour::Rgb),
            "layer" => Some(Colour::Layer),
            f if is_field_name(f) => Some(Colour::Field(f.to_string())),
            _ => None,
        }
    }
}

/// A PLY property name as the studio accepts it in a link: 1-64 of `[A-Za-z0-9_]`.
fn is_field_name(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
}

/// Navigation mode of the mouse and keys.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Nav {
    /// Drag turns the camera around its target; the wheel zooms.
    Orbit,
    /// Drag turns the camera where it stands; W/A/S/D/Q/E move it.
    Fly,
}

/// Everything a share link restores.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewState {
    pub sources: Vec<String>,
    /// `None`: fit the loaded layers.
    pub camera: Option<Camera>,
    pub colour: Colour,
    /// The uncertainty the threshold applies to.
    pub filter: String,
    /// `None`: the default rule (Tukey's fence over the loaded layers).
    pub threshold: Option<f32>,
    pub point_size: f32,
    /// Indices of hidden layers.
    pub hidden: Vec<u32>,
    /// Dark (true) or light background.
    pub dark: bool,
    pub nav: Nav,
    /// Points a COPC map loads at once; `None`: the adapter's default (lower on a software one).
    pub budget: Option<u64>,
    /// The point draw: the compute rasteriser (default) or the instanced quads it is checked against.
    pub draw: Raster,
}

impl Default for ViewState {
    fn default() -> Self {
        Self {
            sources: Vec::new(),
            camera: None,
            colour: Colour::Rgb,
            filter: "log_std_combined".into(),
            threshold: None,
            point_size: 2.0,
            hidden: Vec::new(),
            dark: true,
            nav: Nav::Orbit,
            budget: None,
            draw: Raster::Compute,
        }
    }
}

/// Whether `url` is one the studio may fetch: `http:` or `https:`, printable ASCII without spaces, at
/// most [`MAX_URL_BYTES`]. (The browser's URL parser and fetch do the rest.)
pub fn is_fetchable(url: &str) -> bool {
    let lower = url.get(..8).unwrap_or(url).to_ascii_lowercase();
    (lower.starts_with("http://") || lower.starts_with("https://"))
        && url.len() > "http://".len()
        && url.len() <= MAX_URL_BYTES
        && url.bytes().all(|b| b.is_ascii_graphic())
}

/// RFC 3986 percent-encoding (unreserved characters kept, uppercase hex), as `silvr serve` writes links.
pub fn encode(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// Percent-decoding to bytes; `None` on a bad escape (`%` not followed by two hex digits).
pub fn decode_bytes(s: &str) -> Option<Vec<u8>> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = b.get(i + 1..i + 3)?;
            let digit = |c: u8| (c as char).to_digit(16);
            out.push((digit(hex[0])? * 16 + digit(hex[1])?) as u8);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    Some(out)
}

/// Percent-decoding; `None` on a bad escape or bytes that are not UTF-8.
pub fn decode(s: &str) -> Option<String> {
    String::from_utf8(decode_bytes(s)?).ok()
}

/// The access token in a page's query (`location.search`, with or without its `?`): the first
/// `token=` parameter, decoded, if it is a non-empty printable ASCII string of at most
/// [`MAX_TOKEN_BYTES`] (anything else could not travel in a header).
pub fn query_token(search: &str) -> Option<String> {
    search
        .trim_start_matches('?')
        .split('&')
        .find_map(|part| part.strip_prefix(TOKEN_PARAM)?.strip_prefix('='))
        .and_then(decode)
        .filter(|t| {
            !t.is_empty() && t.len() <= MAX_TOKEN_BYTES && t.bytes().all(|b| b.is_ascii_graphic())
        })
}

/// A page's query without its access token, as a share link keeps it: `?a=1&token=x&b=2` → `?a=1&b=2`,
/// `""` when nothing is left.
pub fn query_without_token(search: &str) -> String {
    let kept: Vec<&str> = search
        .trim_start_matches('?')
        .split('&')
        .filter(|p| !p.is_empty() && p.split('=').next() != Some(TOKEN_PARAM))
        .collect();
    if kept.is_empty() {
        String::new()
    } else {
        format!("?{}", kept.join("&"))
    }
}

fn numbers<const N: usize>(s: &str) -> Option<[f64; N]> {
    let mut out = [0.0; N];
    let mut parts = s.split(',');
    for v in &mut out {
        let x: f64 = parts.next()?.trim().parse().ok()?;
        if !x.is_finite() {
            return None;
        }
        *v = x;
    }
    parts.next().is_none().then_some(out)
}

impl ViewState {
    /// The hash (with its leading `#`) that restores this view.
    pub fn to_hash(&self) -> String {
        let mut p: Vec<String> = self
            .sources
            .iter()
            .map(|s| format!("src={}", encode(s)))
            .collect();
        if let Some(c) = &self.camera {
            p.push(format!(
                "cam={},{},{},{},{},{},{}",
                c.target[0], c.target[1], c.target[2], c.yaw, c.pitch, c.distance, c.fov
            ));
        }
        p.push(format!("colour={}", encode(self.colour.as_param())));
        p.push(format!("filter={}", encode(&self.filter)));
        if let Some(t) = self.threshold {
            p.push(format!("t={t}"));
        }
        p.push(format!("size={}", self.point_size));
        if !self.hidden.is_empty() {
            let h: Vec<String> = self.hidden.iter().map(|i| i.to_string()).collect();
            p.push(format!("hide={}", h.join(",")));
        }
        p.push(format!("bg={}", if self.dark { "dark" } else { "light" }));
        p.push(format!(
            "nav={}",
            match self.nav {
                Nav::Orbit => "orbit",
                Nav::Fly => "fly",
            }
        ));
        if let Some(b) = self.budget {
            p.push(format!("budget={b}"));
        }
        if self.draw != Raster::default() {
            p.push(format!("draw={}", self.draw.name()));
        }
        format!("#{}", p.join("&"))
    }

    /// Parses a hash (leading `#` optional). Never fails: what cannot be used is dropped and described
    /// in the returned notes (one sentence each, naming the parameter), and defaults stand in.
    pub fn from_hash(hash: &str) -> (Self, Vec<String>) {
        let mut s = Self::default();
        let mut notes = Vec::new();
        let hash = hash.strip_prefix('#').unwrap_or(hash);
        if hash.len() > MAX_HASH_BYTES {
            notes.push(format!(
                "the link's view is {} bytes, more than the {MAX_HASH_BYTES} the studio reads; it was ignored",
                hash.len()
            ));
            return (s, notes);
        }
        for part in hash.split('&').filter(|p| !p.is_empty()) {
            let (key, raw) = part.split_once('=').unwrap_or((part, ""));
            let Some(value) = decode(raw) else {
                notes.push(format!("'{}' has a malformed value; ignored", short(key)));
                continue;
            };
            let mut bad = |what: &str| {
                notes.push(format!("'{}' {what}; ignored", short(key)));
            };
            match key {
                "src" => {
                    if s.sources.len() >= MAX_SOURCES {
                        bad(&format!("is over the limit of {MAX_SOURCES} sources"));
                    } else if is_fetchable(&value) {
                        s.sources.push(value);
                    } else {
                        bad("is not an http(s) URL the studio may fetch");
                    }
                }
                "cam" => match numbers::<7>(&value) {
                    Some(v) => {
                        let c = Camera {
                            target: [v[0], v[1], v[2]],
                            yaw: v[3],
                            pitch: v[4],
                            distance: v[5],
                            fov: v[6],
                        };
                        match c.clamped() {
                            Some(c) => s.camera = Some(c),
                            None => bad("is not a usable camera"),
                        }
                    }
                    None => bad("must be seven finite numbers"),
                },
                "colour" => match Colour::from_param(&value) {
                    Some(c) => s.colour = c,
                    None => bad("is not a colour mode"),
                },
                "filter" if is_field_name(&value) => s.filter = value,
                "filter" => bad("is not a property name"),
                "t" => match value.parse::<f32>() {
                    Ok(t) if t.is_finite() => s.threshold = Some(t),
                    _ => bad("must be a finite number"),
                },
                "size" => match value.parse::<f32>() {
                    Ok(v) if v.is_finite() => s.point_size = v.clamp(POINT_SIZE.0, POINT_SIZE.1),
                    _ => bad("must be a finite number"),
                },
                "hide" => {
                    let v: Option<Vec<u32>> = value
                        .split(',')
                        .filter(|x| !x.is_empty())
                        .take(MAX_SOURCES + 1)
                        .map(|x| {
                            x.parse::<u32>()
                                .ok()
                                .filter(|&i| (i as usize) < MAX_SOURCES)
                        })
                        .collect();
                    match v {
                        Some(mut v) if v.len() <= MAX_SOURCES => {
                            v.sort_unstable();
                            v.dedup();
                            s.hidden = v;
                        }
                        _ => bad("must be layer numbers below 16"),
                    }
                }
                "bg" => match value.as_str() {
                    "dark" => s.dark = true,
                    "light" => s.dark = false,
                    _ => bad("must be dark or light"),
                },
                "nav" => match value.as_str() {
                    "orbit" => s.nav = Nav::Orbit,
                    "fly" => s.nav = Nav::Fly,
                    _ => bad("must be orbit or fly"),
                },
                "budget" => match value.parse::<u64>() {
                    Ok(b) => s.budget = Some(b.clamp(BUDGET_RANGE.0, BUDGET_RANGE.1)),
                    _ => bad("must be a whole number of points"),
                },
                "draw" => match Raster::parse(&value) {
                    Some(r) => s.draw = r,
                    None => bad("must be compute or quads"),
                },
                _ => {}
            }
        }
        (s, notes)
    }
}

/// A key as quoted in a note: at most 24 printable characters.
fn short(key: &str) -> String {
    key.chars().filter(|c| !c.is_control()).take(24).collect()
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn random_state(rng: &mut Xoshiro256PlusPlus) -> ViewState {
        let n = rng.random_range(0..4);
        let sources = (0..n)
            .map(|i| {
                format!(
                    "http{}://127.0.0.1:{}/data/sub dir/p {i}&x=1#?.ply",
                    if rng.random() { "s" } else { "" },
                    rng.random_range(1..65535)
                )
                .replace(' ', "%20")
            })
            .collect();
        let camera = rng.random::<bool>().then(|| Camera {
            target: [
                rng.random_range(-1e5..1e5),
                rng.random_range(-1e5..1e5),
                rng.random_range(-100.0..100.0),
            ],
            yaw: rng.random_range(0.0..360.0),
            pitch: rng.random_range(-89.0..89.0),
            distance: rng.random_range(0.01..1e4),
            fov: rng.random_range(5.0..120.0),
        });
        let colours = ["rgb", "layer", "log_std_depth", "error_m"];
        ViewState {
            sources,
            camera,
            colour: Colour::from_param(colours[rng.random_range(0..4)]).unwrap(),
            filter: ["log_std_combined", "log_std_colour"][rng.random_range(0..2)].into(),
            threshold: rng.random::<bool>().then(|| rng.random_range(-4.0..2.0)),
            point_size: rng.random_range(1.0..32.0),
            hidden: if rng.random() { vec![0, 3] } else { vec![] },
            dark: rng.random(),
            nav: if rng.random() { Nav::Orbit } else { Nav::Fly },
            budget: rng
                .random::<bool>()
                .then(|| rng.random_range(BUDGET_RANGE.0..=BUDGET_RANGE.1)),
            draw: if rng.random() {
                Raster::Compute
            } else {
                Raster::Quads
            },
        }
    }

    /// Property: every state survives its link exactly (floats print in Rust's shortest round-trip form).
    #[test]
    fn a_link_restores_the_same_view() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
        for _ in 0..2000 {
            let s = random_state(&mut rng);
            let (back, notes) = ViewState::from_hash(&s.to_hash());
            assert!(notes.is_empty(), "{notes:?} for {}", s.to_hash());
            assert_eq!(back, s, "{}", s.to_hash());
            // The camera matrix is the same too.
            if let Some(c) = s.camera {
                let r = DVec3::from_array(c.target);
                assert_eq!(
                    c.view_proj((800, 600), 10.0, r),
                    back.camera.unwrap().view_proj((800, 600), 10.0, r)
                );
            }
        }
    }

    #[test]
    fn hostile_links_are_dropped_with_a_note() {
        for bad in [
            "javascript:alert(1)",
            "JavaScript:alert(1)",
            "data:text/html,<script>alert(1)</script>",
            "file:///etc/passwd",
            "blob:http://x/1",
            "//evil.example/x.ply",
            "http://",
            "http://a b",
        ] {
            let (s, notes) = ViewState::from_hash(&format!("#src={}", encode(bad)));
            assert!(s.sources.is_empty(), "{bad} was accepted");
            assert_eq!(notes.len(), 1, "{bad}: {notes:?}");
            assert!(notes[0].contains("'src'"), "{notes:?}");
        }
        let (s, notes) = ViewState::from_hash(
            "#cam=1,2,3,nan,0,1,60&t=inf&size=1e999&colour=%3Cimg%3E&hide=99&bg=x&nav=&src=%ZZ&budget=-1&draw=gl",
        );
        assert_eq!(s, ViewState::default());
        assert_eq!(notes.len(), 10, "{notes:?}");
        assert!(notes.iter().any(|n| n.contains("'draw'")), "{notes:?}");
        // A budget out of range is brought into it.
        let (s, notes) = ViewState::from_hash("#budget=3&x=1");
        assert_eq!((s.budget, notes.len()), (Some(BUDGET_RANGE.0), 0));
        let (s, _) = ViewState::from_hash("#budget=18446744073709551615");
        assert_eq!(s.budget, Some(BUDGET_RANGE.1));
        // Over-long hashes are not parsed at all.
        let (s, notes) = ViewState::from_hash(&"src=http://a/b&".repeat(5000));
        assert!(s.sources.is_empty() && notes.len() == 1);
        // At most 16 sources.
        let (s, notes) = ViewState::from_hash(&"src=http%3A%2F%2Fa%2Fb&".repeat(20));
        assert_eq!(s.sources.len(), MAX_SOURCES);
        assert_eq!(notes.len(), 4);
    }

    /// Property: no input panics, and whatever is accepted is within its bounds.
    #[test]
    fn random_bytes_never_panic() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(9);
        let alphabet =
            b"src=cam&colour=t=size=hide=budget=draw=quads,.-0123456789%eE#:/httpsjavascript";
        for _ in 0..20_000 {
            let n = rng.random_range(0..120);
            let s: String = (0..n)
                .map(|_| {
                    if rng.random_range(0..8) == 0 {
                        char::from_u32(rng.random_range(0..0x11000)).unwrap_or('?')
                    } else {
                        alphabet[rng.random_range(0..alphabet.len())] as char
                    }
                })
                .collect();
            let (v, _) = ViewState::from_hash(&s);
            assert!(v.sources.iter().all(|u| is_fetchable(u)));
            assert!((POINT_SIZE.0..=POINT_SIZE.1).contains(&v.point_size));
            if let Some(c) = v.camera {
                assert!(c.distance > 0.0 && (5.0..=120.0).contains(&c.fov));
            }
            if let Some(b) = v.budget {
                assert!((BUDGET_RANGE.0..=BUDGET_RANGE.1).contains(&b));
            }
        }
    }

    #[test]
    fn percent_encoding_matches_silvr_serve() {
        assert_eq!(
            encode("http://127.0.0.1:8080/data/silvr/points.ply"),
            "http%3A%2F%2F127.0.0.1%3A8080%2Fdata%2Fsilvr%2Fpoints.ply"
        );
        assert_eq!(decode("a%20b%2Fc").as_deref(), Some("a b/c"));
        assert_eq!(decode("%4"), None);
        assert_eq!(decode("%FF"), None);
        assert_eq!(decode("%+1"), None);
        assert_eq!(decode_bytes("%FF%e9"), Some(vec![0xFF, 0xE9]));
        assert_eq!(decode("é%C3%A9").as_deref(), Some("éé"));
    }

    #[test]
    fn fit_frames_the_box() {
        let c = Camera::fit([0.0, 0.0, 0.0], [10.0, 20.0, 4.0]);
        assert_eq!(c.target, [5.0, 10.0, 2.0]);
        let half = 0.5 * (10.0f64 * 10.0 + 400.0 + 16.0).sqrt();
        assert!(c.distance * (30f64.to_radians()).tan() > half);
    }

    #[test]
    fn the_token_is_read_from_the_query_and_left_out_of_share_links() {
        assert_eq!(query_token("?token=abc123").as_deref(), Some("abc123"));
        assert_eq!(
            query_token("train=x&token=a%2Db&token=second").as_deref(),
            Some("a-b")
        );
        for none in [
            "",
            "?",
            "?tokens=abc",
            "?token",
            "?token=",
            "?token=%zz",
            "?token=a%20b",
            "?token=%0A",
            "?xtoken=abc",
        ] {
            assert_eq!(query_token(none), None, "{none}");
        }
        assert_eq!(
            query_token(&format!("?token={}", "a".repeat(MAX_TOKEN_BYTES + 1))),
            None
        );

        assert_eq!(query_without_token("?token=abc"), "");
        assert_eq!(query_without_token(""), "");
        assert_eq!(
            query_without_token("?url=x&token=abc&steps=3&token"),
            "?url=x&steps=3"
        );
        assert_eq!(query_without_token("tokens=1&&a=2"), "?tokens=1&a=2");
        // What a share link keeps never carries a token a page would read.
        for q in ["?token=abc&a=1", "?a=1&token=abc", "?token&token=abc"] {
            assert_eq!(query_token(&query_without_token(q)), None, "{q}");
        }
    }
}
