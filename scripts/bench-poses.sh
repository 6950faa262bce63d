#!/usr/bin/env bash
# Pose refinement side by side (issue 18 item 5): `silvr poses` against COLMAP 3.8 on the same images.
#
#   scripts/bench-poses.sh [DATASET]
#
# DATASET is a synthetic world (transforms_prior.json = the SLAM-like prior, transforms.json = the exact
# poses); default: a fresh `silvr synth --preset ci` world in the work folder. One run does
#   a. ours:   silvr poses DATASET/transforms_prior.json --gt DATASET/transforms.json
#   b. COLMAP 3.8 with the prior (../shared/reference/sfm.md §4), CPU only: feature_extractor per camera
#      with that camera's calibration (and the sky masks), matches_importer on OUR candidate pairs
#      (silvr pairs), point_triangulator on the prior poses, bundle_adjuster (extrinsics only),
#      model_aligner to the prior's camera centres, model_converter to text
#   c. COLMAP's free mapper (no prior poses; same features and matches) + model_aligner, under a timeout
# then scores prior / ours / COLMAP against the exact poses with `silvr eval-poses` (COLMAP's text model
# read directly), computes every model's reprojection RMSE with one formula, prints a table and writes a
# JSON summary. COLMAP is installed with apt when missing; it is never a product dependency.
#
# Environment:
#   OUT=FILE          summary JSON (default target/bench-poses/summary.json)
#   WORK=DIR          work folder (default: a new /tmp/bench-poses.XXXXXX, kept for inspection)
#   SILVR=BIN         use this silvr binary (no build)
#   PROFILE=release   cargo profile to build silvr with (release | dev); the build time is recorded
#   THREADS=N         COLMAP's threads (default nproc)
#   FREE_MAPPER=1     run the no-prior mapper baseline (0: skip); FREE_TIMEOUT=900 seconds
#   MASKS=1           give COLMAP the sky masks (0: none)
#   COLMAP_PEAK=0.0025 COLMAP_MAX_FEATURES=4096
#                     COLMAP's SIFT peak threshold and feature cap: by default the ones `silvr poses` uses
#                     (our SIFT follows COLMAP 3.8's otherwise); COLMAP's own defaults are 0.00667 and 8192
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
HELPER="$ROOT/scripts/bench_poses_helper.py"
OUT="${OUT:-$ROOT/target/bench-poses/summary.json}"
WORK="${WORK:-$(mktemp -d /tmp/bench-poses.XXXXXX)}"
THREADS="${THREADS:-$(nproc)}"
PROFILE="${PROFILE:-release}"
FREE_MAPPER="${FREE_MAPPER:-1}"
FREE_TIMEOUT="${FREE_TIMEOUT:-900}"
MASKS="${MASKS:-1}"
COLMAP_PEAK="${COLMAP_PEAK:-0.0025}"
COLMAP_MAX_FEATURES="${COLMAP_MAX_FEATURES:-4096}"
export QT_QPA_PLATFORM=offscreen # headless COLMAP

mkdir -p "$WORK/logs"
WORK="$(cd "$WORK" && pwd)"
: >"$WORK/times.tsv"
say() { printf '[bench-poses] %s\n' "$*" >&2; }

# run NAME CMD...: runs CMD with its output in logs/NAME.log; appends "NAME seconds max_rss_kb cpu% rc" to
# times.tsv; a failure stops the script unless ALLOW_FAIL=1 (then the status is returned).
run() {
	local name=$1
	shift
	local log="$WORK/logs/$name.log" tfile="$WORK/logs/$name.time" t0 t1 rc=0
	t0=$(date +%s.%N)
	if [ -x /usr/bin/time ]; then
		/usr/bin/time -v -o "$tfile" "$@" >"$log" 2>&1 || rc=$?
	else
		"$@" >"$log" 2>&1 || rc=$?
	fi
	t1=$(date +%s.%N)
	local secs rss="" cpu=""
	secs=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", b - a }')
	if [ -f "$tfile" ]; then
		rss=$(awk -F': ' '/Maximum resident set size/ { print $2 }' "$tfile")
		cpu=$(awk -F': ' '/Percent of CPU/ { gsub("%", "", $2); print $2 }' "$tfile")
	fi
	printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$secs" "$rss" "$cpu" "$rc" >>"$WORK/times.tsv"
	say "$name: ${secs} s (rc $rc)"
	if [ "$rc" -ne 0 ] && [ "${ALLOW_FAIL:-0}" != 1 ]; then
		say "$name failed; the end of $log:"
		tail -n 30 "$log" >&2
		exit "$rc"
	fi
	return "$rc"
}

# --- tools ---------------------------------------------------------------------------------------------
if ! command -v colmap >/dev/null; then
	say "installing COLMAP (Debian's 3.8) with apt"
	SUDO=""
	[ "$(id -u)" -eq 0 ] || SUDO=sudo
	$SUDO apt-get update -qq
	DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq colmap >/dev/null
fi
COLMAP_VERSION=$( (colmap -h 2>&1 || true) | sed -n '1s/ -- .*//p')
command -v python3 >/dev/null || {
	say "python3 is needed (standard library only)"
	exit 1
}

BUILD_S=null
if [ -n "${SILVR:-}" ]; then
	BUILD_PROFILE="given"
else
	TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
	say "building silvr ($PROFILE profile)"
	t0=$(date +%s.%N)
	if [ "$PROFILE" = release ]; then
		(cd "$ROOT" && cargo build --release --bin silvr)
		SILVR="$TARGET/release/silvr"
	else
		(cd "$ROOT" && cargo build --bin silvr)
		SILVR="$TARGET/debug/silvr"
	fi
	BUILD_S=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
	BUILD_PROFILE="$PROFILE"
	say "build: ${BUILD_S} s"
fi
SILVR="$(cd "$(dirname "$SILVR")" && pwd)/$(basename "$SILVR")"

# --- the dataset ---------------------------------------------------------------------------------------
if [ $# -ge 1 ]; then
	DATASET="$(cd "$1" && pwd)"
else
	DATASET="$WORK/world"
	say "synthesising the ci world into $DATASET"
	run synth "$SILVR" synth --preset ci --out "$DATASET"
fi
PRIOR="$DATASET/transforms_prior.json"
EXACT="$DATASET/transforms.json"
for f in "$PRIOR" "$EXACT"; do
	[ -f "$f" ] || {
		say "$f is missing (a synthetic world holds both the prior and the exact poses)"
		exit 1
	}
done
say "dataset $DATASET, work folder $WORK, COLMAP threads $THREADS"

# --- a. ours -------------------------------------------------------------------------------------------
rm -rf "$WORK/ours"
run ours "$SILVR" poses "$PRIOR" --out "$WORK/ours" --gt "$EXACT"

# --- b. COLMAP with the prior --------------------------------------------------------------------------
C="$WORK/colmap"
rm -rf "$C"
mkdir -p "$C/sparse/prior" "$C/sparse/tri" "$C/sparse/ba" "$C/sparse/aligned" "$C/txt"
DB="$C/database.db"
python3 "$HELPER" cameras "$PRIOR" "$C/cams" >"$C/cameras.names"
MASK_ARGS=()
MASK_INFO=null
if [ "$MASKS" = 1 ] && grep -q sky_mask_path "$PRIOR"; then
	MASK_INFO=$(python3 "$HELPER" masks "$PRIOR" "$C/masks")
	MASK_ARGS=(--ImageReader.mask_path "$C/masks")
fi
# feature_extractor once per camera (each run makes its camera, with its own calibration, fixed); the
# summary adds the runs up as "colmap_features".
while read -r cam; do
	IFS=$'\t' read -r model params <"$C/cams/$cam.params"
	run "colmap_features_$cam" colmap feature_extractor --database_path "$DB" --image_path "$DATASET" \
		--image_list_path "$C/cams/$cam.list" "${MASK_ARGS[@]}" \
		--ImageReader.camera_model "$model" --ImageReader.single_camera 1 \
		--ImageReader.camera_params "$params" \
		--SiftExtraction.use_gpu 0 --SiftExtraction.num_threads "$THREADS" \
		--SiftExtraction.peak_threshold "$COLMAP_PEAK" --SiftExtraction.max_num_features "$COLMAP_MAX_FEATURES"
done <"$C/cameras.names"
run pairs "$SILVR" pairs "$PRIOR" --out "$C/pairs.txt"
run colmap_matches_importer colmap matches_importer --database_path "$DB" \
	--match_list_path "$C/pairs.txt" --match_type pairs \
	--SiftMatching.use_gpu 0 --SiftMatching.num_threads "$THREADS"
python3 "$HELPER" dbstats "$DB" >"$WORK/dbstats.json"
# The prior as a model with the database's ids (untimed bookkeeping, as ours reads the prior itself).
"$SILVR" export colmap "$PRIOR" --out "$C/prior_export" >/dev/null
python3 "$HELPER" prior "$DB" "$C/prior_export" "$C/sparse/prior" >/dev/null
python3 "$HELPER" centres "$PRIOR" "$C/ref_centres.txt"
run colmap_point_triangulator colmap point_triangulator --database_path "$DB" --image_path "$DATASET" \
	--input_path "$C/sparse/prior" --output_path "$C/sparse/tri" \
	--Mapper.tri_min_angle 1.5 --Mapper.filter_max_reproj_error 4 --Mapper.num_threads "$THREADS"
run colmap_bundle_adjuster colmap bundle_adjuster --input_path "$C/sparse/tri" --output_path "$C/sparse/ba" \
	--BundleAdjustment.refine_extrinsics 1 --BundleAdjustment.refine_focal_length 0 \
	--BundleAdjustment.refine_principal_point 0 --BundleAdjustment.refine_extra_params 0 \
	--BundleAdjustment.max_num_iterations 100
run colmap_model_aligner colmap model_aligner --input_path "$C/sparse/ba" --output_path "$C/sparse/aligned" \
	--ref_images_path "$C/ref_centres.txt" --ref_is_gps 0 --alignment_type custom --estimate_scale 1 \
	--robust_alignment 1 --robust_alignment_max_error 0.10 --transform_path "$C/sim3.txt"
run colmap_model_converter colmap model_converter --input_path "$C/sparse/aligned" --output_path "$C/txt" \
	--output_type TXT

# --- c. COLMAP without the prior -----------------------------------------------------------------------
F="$WORK/colmap_free"
FREE_OK=0
if [ "$FREE_MAPPER" = 1 ]; then
	rm -rf "$F"
	mkdir -p "$F/sparse" "$F/aligned" "$F/txt"
	if ALLOW_FAIL=1 run colmap_mapper timeout "$FREE_TIMEOUT" colmap mapper --database_path "$DB" \
		--image_path "$DATASET" --output_path "$F/sparse" --Mapper.num_threads "$THREADS" \
		--Mapper.multiple_models 0 --Mapper.ba_refine_focal_length 0 \
		--Mapper.ba_refine_principal_point 0 --Mapper.ba_refine_extra_params 0 &&
		[ -d "$F/sparse/0" ] &&
		ALLOW_FAIL=1 run colmap_free_model_aligner colmap model_aligner --input_path "$F/sparse/0" --output_path "$F/aligned" \
			--ref_images_path "$C/ref_centres.txt" --ref_is_gps 0 --alignment_type custom \
			--estimate_scale 1 --robust_alignment 1 --robust_alignment_max_error 0.10 \
			--transform_path "$F/sim3.txt"; then
		run colmap_free_model_converter colmap model_converter --input_path "$F/aligned" \
			--output_path "$F/txt" --output_type TXT
		FREE_OK=1
	else
		say "the free mapper's model is missing or could not be aligned to the prior (timeout ${FREE_TIMEOUT} s," \
			"failure, or too few images): see $WORK/logs/colmap_mapper.log, colmap_free_model_aligner.log"
		# Still score what it registered, in its own frame (eval-poses aligns by Sim(3) itself).
		if [ -d "$F/sparse/0" ]; then
			colmap model_converter --input_path "$F/sparse/0" --output_path "$F/txt" --output_type TXT \
				>/dev/null 2>&1 && FREE_OK=1
		fi
	fi
fi

# --- scores --------------------------------------------------------------------------------------------
score() { # score NAME EST
	"$SILVR" eval-poses --est "$2" --gt "$EXACT" --out "$WORK/eval_$1.json" 2>"$WORK/logs/eval_$1.log" ||
		say "eval-poses of $1 failed: $(cat "$WORK/logs/eval_$1.log")"
}
analyzer() { # the "Mean reprojection error" of colmap model_analyzer
	colmap model_analyzer --path "$1" 2>&1 | sed -n 's/.*Mean reprojection error: *\([0-9.eE+-]*\)px.*/\1/p' | tail -n 1
}
score prior "$PRIOR"
score ours "$WORK/ours/transforms.json"
score colmap_prior "$C/txt"
python3 "$HELPER" reproj "$WORK/ours/colmap" >"$WORK/reproj_ours.json"
python3 "$HELPER" reproj "$C/txt" >"$WORK/reproj_colmap_prior.json"
A_OURS=$(analyzer "$WORK/ours/colmap")
A_PRIOR=$(analyzer "$C/txt")
A_FREE=""
if [ "$FREE_OK" = 1 ]; then
	score colmap_free "$F/txt"
	python3 "$HELPER" reproj "$F/txt" >"$WORK/reproj_colmap_free.json"
	A_FREE=$(analyzer "$F/txt")
fi

num_or_null() { [ -n "$1" ] && echo "$1" || echo null; }
cat >"$WORK/meta.json" <<EOF
{
  "date": "$(date -u +%Y-%m-%dT%H:%M:%SZ)",
  "dataset": "$DATASET",
  "work": "$WORK",
  "nproc": $(nproc),
  "cpu": "$(grep -m1 'model name' /proc/cpuinfo | sed 's/.*: //')",
  "colmap_threads": $THREADS,
  "colmap": "$COLMAP_VERSION",
  "silvr": "$SILVR",
  "silvr_profile": "$BUILD_PROFILE",
  "build_s": $BUILD_S,
  "masks": $MASK_INFO,
  "colmap_sift": {"peak_threshold": $COLMAP_PEAK, "max_num_features": $COLMAP_MAX_FEATURES},
  "analyzer_ours": $(num_or_null "$A_OURS"),
  "analyzer_colmap_prior": $(num_or_null "$A_PRIOR"),
  "analyzer_colmap_free": $(num_or_null "$A_FREE")
}
EOF
python3 "$HELPER" summary "$WORK" "$OUT"
