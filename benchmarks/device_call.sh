#!/usr/bin/env bash
# One call on a bare GPU machine: install the wheels that its image lacks, then run the named
# benchmark stages in order, each under its own time limit, logging everything to one file.
#
#   bash benchmarks/device_call.sh STAGE [STAGE ...]
#
# Expects, beside the checkout: .whl/ (trimesh, openexr, colour-science wheels for Python 3.12)
# and .gpudata/ (a copy of the data folder: meshes/, brdfs/), both carried with the tree; optionally
# .mitsuba/mitsuba.tar.xz (`benchmarks/mitsuba_carry.py`) for the stages that run Mitsuba beside jaxrt.
# Writes $OUT/log.txt and the stages' JSON/NPZ/PNG files under $OUT (at most 8 files come back).
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
LOG="$OUT/log.txt"
export PYTHONUNBUFFERED=1 JAXRT_DATA="$PWD/.gpudata" JAXRT_CACHE_DIR=${JAXRT_CACHE_DIR:-/tmp/jaxrt-cache}
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        >>"$LOG" 2>&1 || { echo "wheel install failed" | tee -a "$LOG"; exit 1; }
    export PYTHONPATH="/tmp/site:$PWD"
    # byte-compile what the wheels (installed with --no-compile) and the checkout hold, as an ordinary
    # install does: otherwise every process of a latency stage recompiles ~180 modules (~0.45 s)
    python3 -m compileall -q -j 0 /tmp/site "$PWD/jaxrt" "$PWD/brdfs" "$PWD/fitting" >>"$LOG" 2>&1
else
    export PYTHONPATH="$PWD"
fi
if [ -f .mitsuba/mitsuba.tar.xz ]; then
    # Mitsuba 3 and Dr.Jit, trimmed to the benchmarks' variant and plugins (`benchmarks/mitsuba_carry.py`):
    # the whole wheel is too large to carry
    mkdir -p /tmp/site && tar xJf .mitsuba/mitsuba.tar.xz -C /tmp/site >>"$LOG" 2>&1 \
        && export PYTHONPATH="/tmp/site:${PYTHONPATH}" || echo "mitsuba unpack failed" | tee -a "$LOG"
fi
{ date -u; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc;
  python3 -c "import jax, sys; print('python', sys.version.split()[0], 'jax', jax.__version__, jax.devices())";
  git log -1 --format='commit %h %s' 2>/dev/null; } >>"$LOG" 2>&1

stage() {  # stage NAME LIMIT_S COMMAND...
    local name=$1 limit=$2; shift 2
    echo "=== $name: $* (limit ${limit}s) $(date -u +%T)" | tee -a "$LOG"
    local t0=$SECONDS
    timeout "$limit" "$@" >>"$LOG" 2>&1
    echo "=== $name: exit $? in $((SECONDS - t0)) s" | tee -a "$LOG"
}

for s in "$@"; do
    case $s in
        frames)   stage frames 150 python3 benchmarks/gpu.py --impls pallas --repeats 5 --skip check --json "$OUT/frames.json" ;;
        glass)    # the same frames with Whitted's glass shadows transmitting (default) and opaque, one run
                  stage glass-transmit 70 python3 benchmarks/gpu.py --impls pallas --repeats 5 --skip rays check --scenes showcase dragon
                  stage glass-opaque 70 python3 benchmarks/gpu.py --impls pallas --repeats 5 --skip rays check --scenes showcase dragon \
                      --override render.glass_shadows=opaque ;;
        study)    stage study 240 python3 benchmarks/brdf_study.py --materials 100 --runs 2 --json "$OUT/study.json" ;;
        image)    stage image-study 200 python3 benchmarks/image_study.py --models cook_torrance,ward,ashikhmin_shirley \
                      --runs 1 --json "$OUT/image.json" ;;
        path)     stage path 80 python3 benchmarks/path.py --size 512 --spp 4 --passes 5 --no-mitsuba ;;
        sppm)     stage sppm 90 python3 benchmarks/sppm.py --size 128 --passes 8 ;;
        latency)  stage latency 420 python3 benchmarks/latency.py --no-mitsuba --worker --warm-runs 3 --json "$OUT/latency.json" \
                      --cases render-dragon render-spheres fit-demo fit-bunny fit-cli sweep-frame import-jaxrt import-brdfs import-fitting ;;
        caustic)  # a converged path-traced reference of the area-light caustic, then SPPM vs path at equal time
                  # (131k spp of full frames, then only the caustic's window, 3 pixels around it)
                  stage caustic-ref 170 python3 benchmarks/sppm.py --make-reference 1073741824 --max-seconds 100 \
                      --chunk-spp 4096 --crop 3 --crop-after 32 --out "$OUT/caustic_ref.npz"
                  stage caustic-equal-time 110 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference "$OUT/caustic_ref.npz" ;;
        caustic-ref)  # only the reference of `caustic` (to carry as .gpudata/caustic_ref.npz to later calls)
                  stage caustic-ref 170 python3 benchmarks/sppm.py --make-reference 1073741824 --max-seconds 100 \
                      --chunk-spp 4096 --crop 3 --crop-after 32 --out "$OUT/caustic_ref.npz" ;;
        profiles) # kernel by kernel (`benchmarks/gpu_profile.py`): an SPPM pass, path-tracing passes, a direct frame
                  stage profile-sppm 70 python3 benchmarks/gpu_profile.py sppm --size 96 --repeats 20
                  stage profile-path-dragon 70 python3 benchmarks/gpu_profile.py path-dragon --size 512 --repeats 5
                  stage profile-path-cornell 50 python3 benchmarks/gpu_profile.py path-cornell --size 512 --repeats 5
                  stage profile-direct-dragon 60 python3 benchmarks/gpu_profile.py direct-dragon --size 1024 --repeats 10 ;;
        quick)    # after a change to the GPU passes: their profiles, then SPPM vs path at equal time (carried
                  # reference) and the path-tracing rows beside Mitsuba (.mitsuba/ carried)
                  stage profile-sppm 70 python3 benchmarks/gpu_profile.py sppm --size 96 --repeats 20
                  stage profile-path-dragon 70 python3 benchmarks/gpu_profile.py path-dragon --size 512 --repeats 5
                  stage caustic-carried 90 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz --bias-seeds 0
                  stage peers-path 120 python3 benchmarks/peers.py --rows path --repeats 5 ;;
        peers-path)  # only the path-tracing rows beside Mitsuba's cuda_ad_rgb (.mitsuba/ carried)
                  stage peers-path 120 python3 benchmarks/peers.py --rows path --repeats 5 ;;
        hlo)      # the optimised GPU programs of a path-tracing pass and an SPPM call, as text (xz) beside the
                  # kernel profiles: to read which fusions and copies the profiles' kernel names are
                  # (HLO_WORKLOADS="path-cornell": only that one)
                  for w in ${HLO_WORKLOADS:-path-dragon path-cornell sppm}; do
                      size=512; [ "$w" = sppm ] && size=96
                      XLA_FLAGS="--xla_dump_to=/tmp/hlo-$w --xla_dump_hlo_as_text --xla_dump_hlo_pass_re=^$" \
                          stage "hlo-$w" 70 python3 benchmarks/gpu_profile.py "$w" --size "$size" --repeats 3 --top 40
                      big=$(ls -S /tmp/hlo-$w/*after_optimizations.txt 2>/dev/null | head -1)
                      [ -n "$big" ] && xz -c "$big" > "$OUT/hlo-$w.txt.xz"
                  done ;;
        sppm-quick) # after a change to the SPPM pass on the GPU: its profile and the equal-time table
                  stage profile-sppm 70 python3 benchmarks/gpu_profile.py sppm --size 96 --repeats 10
                  stage caustic-carried 90 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz --bias-seeds 0 ;;
        picture-dragon) # README's caustics_dragon picture, path tracing and SPPM at equal time on the GPU
                  stage picture-dragon 150 python3 benchmarks/sppm.py --picture "$OUT/caustics_dragon.png" \
                      --scene caustics_dragon --size 192 --seconds 12 ;;
        latency-goals) # the latency rows with goals on a GPU: cold, 3 warm processes, the worker's later jobs
                  stage latency-goals 300 python3 benchmarks/latency.py --no-mitsuba --worker --warm-runs 3 \
                      --json "$OUT/latency.json" --cases render-dragon render-spheres fit-cli sweep-frame ;;
        caustic-calls)  # after `caustic` (its reference; or CAUSTIC_REF=.gpudata/caustic_ref.npz, carried): SPPM
                  # passes per compiled call and grid levels. Throughput of the equal-time frame (96x72, the GPU
                  # defaults: 4 visible points, 65,536 photons), one pass a call against passes_per_call's choice,
                  # with 2 and 1 grid levels; then the equal-time table with one pass a call (as before passes per
                  # call) and with 1 grid level. With `caustic` in the same call: about 9.5 minutes together
                  ref=${CAUSTIC_REF:-$OUT/caustic_ref.npz}
                  for L in 2 1; do
                      stage "caustic-calls-throughput-L$L" 75 python3 benchmarks/sppm.py --throughput-scene equal-time \
                          --size 96 --photons 65536 --camera-samples 4 --grid-levels "$L" --passes 30
                  done
                  stage caustic-calls-one-a-call 60 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference "$ref" --passes-per-call 1 --bias-seeds 0
                  stage caustic-calls-L1 60 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference "$ref" --grid-levels 1 --bias-seeds 0 ;;
        caustic-sweep)  # after `caustic` (its reference): SPPM's visible points per pixel and photons per pass
                  for cfg in "1 262144" "4 65536" "16 65536" "16 262144" "64 65536"; do
                      read -r k p <<< "$cfg"
                      stage "caustic-sweep-k$k-p$p" 75 python3 benchmarks/sppm.py --equal-time 0.25,1,4 \
                          --reference "$OUT/caustic_ref.npz" --camera-samples "$k" --photons "$p" --bias-seeds 0
                  done ;;
        caustic-small)  # the same with a 0.1 m lamp of the same power (9x smaller solid angle)
                  stage caustic-small-ref 150 python3 benchmarks/sppm.py --lamp 0.1 --make-reference 4194304 \
                      --max-seconds 90 --out "$OUT/caustic_ref_small.npz"
                  stage caustic-small-equal-time 100 python3 benchmarks/sppm.py --lamp 0.1 --equal-time 0.25,1,4 \
                      --reference "$OUT/caustic_ref_small.npz" --bias-seeds 2 ;;
        caustic-aim)  # equal time against a reference carried in .gpudata/, photon aiming on (the default) and off
                  stage caustic-aim 90 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz
                  stage caustic-aim-65k 60 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz --photons 65536 --bias-seeds 0 ;;
        caustic-carried)  # equal time against the reference carried in .gpudata/ (passes per call as a render picks them)
                  stage caustic-carried 90 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz --bias-seeds 0 ;;
        latency-dragon)  # one latency row: `jaxrt render dragon` 1024², cold then 3 warm processes
                  stage latency-dragon 80 python3 benchmarks/latency.py --no-mitsuba --warm-runs 3 \
                      --json "$OUT/latency_dragon.json" --cases render-dragon ;;
        peers)    stage peers 110 python3 benchmarks/peers.py --size 1024 --no-mitsuba ;;
        peers-mitsuba)  # the same rows with Mitsuba's cuda_ad_rgb in the same run (needs .mitsuba/ carried)
                  stage peers-mitsuba 170 python3 benchmarks/peers.py --size 1024 --repeats 5 ;;
        cli-profile-dragon)  # where a warm `jaxrt render dragon` 1024² process spends its time: a cold run fills
                  # a cache folder, then two warm runs under cProfile (cumulative and own-time tables)
                  d=$(mktemp -d); c=$(mktemp -d)
                  ( cd "$d" && export JAXRT_CACHE_DIR=$c JAXRT_WORKER=off && stage cli-dragon-cold 90 python3 -m jaxrt.cli render dragon --width 1024 --height 1024 )
                  for i in 1 2; do
                      ( cd "$d" && export JAXRT_CACHE_DIR=$c JAXRT_WORKER=off && stage "cli-dragon-warm$i" 60 python3 -m cProfile -o "$d/warm$i.prof" -m jaxrt.cli render dragon --width 1024 --height 1024 )
                  done
                  ( cd "$d" && JAXRT_CACHE_DIR=$c JAXRT_WORKER=off timeout 60 python3 -X importtime -m jaxrt.cli render dragon \
                      --width 1024 --height 1024 >/dev/null 2>"$d/imports2.txt" )
                  python3 - "$d/warm2.prof" >>"$LOG" 2>&1 <<'PY'
import pstats, sys
s = pstats.Stats(sys.argv[1]); s.sort_stats("cumulative").print_stats(45); s.sort_stats("tottime").print_stats(25)
PY
                  sort -t'|' -k2 -n -r "$d/imports2.txt" | head -25 >>"$LOG" ;;
        caustic-sweep-carried)  # SPPM's visible points per pixel (k) and photons per pass (p) against the carried reference
                  for cfg in "4 65536" "16 65536" "32 65536" "16 16384" "64 16384" "16 262144"; do
                      read -r k p <<< "$cfg"
                      stage "caustic-sweep-k$k-p$p" 75 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2 \
                          --reference .gpudata/caustic_ref.npz --camera-samples "$k" --photons "$p" --bias-seeds 0
                  done ;;
        caustic-alpha)  # SPPM's radius reduction α ([render] alpha) and initial radius (pixel footprints, a study
                  # constant: each its own cache folder, stored programs are keyed by source) against the carried reference
                  for cfg in "0.5 1" "0.7 0.5" "0.7 2" "0.5 0.5"; do
                      read -r al rp <<< "$cfg"
                      JAXRT_CACHE_DIR=/tmp/jc-alpha-$al-$rp stage "caustic-alpha$al-r$rp" 75 python3 benchmarks/sppm.py \
                          --equal-time 0.25,0.5,1,2 --reference .gpudata/caustic_ref.npz --alpha "$al" --radius-pixels "$rp" --bias-seeds 0
                  done ;;
        caustic-alpha2)  # α = 0.5 with the bias check, then 0.4 and 0.6, the GPU defaults otherwise
                  stage caustic-alpha0.5 100 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                      --reference .gpudata/caustic_ref.npz --alpha 0.5 --bias-seeds 2
                  for al in 0.4 0.6; do
                      stage "caustic-alpha$al" 75 python3 benchmarks/sppm.py --equal-time 0.25,0.5,1,2,4 \
                          --reference .gpudata/caustic_ref.npz --alpha "$al" --bias-seeds 0
                  done ;;
        chunks)   # live-path compaction (`benchmarks/path_chunks.py`): uncompacted, 2, 3 and 4 chunks per pass (first bounce whole or compacted),
                  # then the dragon pass's kernels with the default
                  stage path-chunks 330 python3 benchmarks/path_chunks.py --size 512 --repeats 5 --chunks 2 3 4 --first whole compacted
                  stage profile-path-dragon 70 python3 benchmarks/gpu_profile.py path-dragon --size 512 --repeats 5 ;;
        chunks-compile)  # the GPU's first bounce on the whole batch or compacted: first-call time (compilation,
                  # no persistent cache) of each in its own process, after an uncompacted pass in the same process
                  for how in whole compacted; do
                      JAXRT_CACHE=off stage "path-first-$how" 120 python3 benchmarks/path_chunks.py --size 512 --repeats 3 \
                          --chunks 4 --first "$how"
                  done ;;
        compact)  # the GPU's bounces compacted in every scene (`path.GPU_COMPACT_MIN_TRIANGLES` 0), in none (10^9), and
                  # the default rule, on the Cornell box, the environment-lit dragon and the same with the bunny
                  stage path-compact 300 python3 benchmarks/path_chunks.py --size 512 --repeats 7 --knobs "" \
                      GPU_COMPACT_MIN_TRIANGLES=0 GPU_COMPACT_MIN_TRIANGLES=1000000000
                  stage path-compact-bunny 120 python3 benchmarks/path_chunks.py --size 512 --repeats 7 --scenes dragon \
                      --mesh bunny --knobs GPU_COMPACT_MIN_TRIANGLES=0 GPU_COMPACT_MIN_TRIANGLES=1000000000 ;;
        profile-path)  # the kernels of a path-tracing pass with the default, Cornell box then dragon
                  stage profile-path-cornell 70 python3 benchmarks/gpu_profile.py path-cornell --size 512 --repeats 5
                  stage profile-path-dragon 70 python3 benchmarks/gpu_profile.py path-dragon --size 512 --repeats 5 ;;
        brute)    # brute force against the tree for small scenes (`benchmarks/brute_force.py`), then the Cornell box's
                  # pass with the tree (the default) and with brute force
                  stage brute-force 240 python3 benchmarks/brute_force.py
                  stage path-brute 120 python3 benchmarks/path_chunks.py --size 512 --repeats 7 --scenes cornell \
                      --knobs "" traverse_pallas.BRUTE_FORCE_MAX_TRIANGLES=64 ;;
        wide)     # the four-wide tree against the binary child-box rows: rays on the Cornell box and the dragon
                  # (`benchmarks/brute_force.py`), then both path-tracing passes with each as the trees' tables
                  stage wide-rays-cornell 150 python3 benchmarks/brute_force.py --splits 0 1 --variants tree wide "wide trail 0"
                  stage wide-rays-dragon 200 python3 benchmarks/brute_force.py --scene dragon --splits 0 \
                      --variants tree wide "wide trail 0"
                  stage path-wide 240 python3 benchmarks/path_chunks.py --size 512 --repeats 7 \
                      --knobs "" traverse_pallas.TREE_LAYOUT=wide ;;
        ncu)      # hardware counters (Nsight Compute, from the machine's CUDA toolkit) of the closest-hit kernel on
                  # the dragon's camera and bounce rays, a gather a word against vector loads and the four-wide tree
                  stage ncu-dragon 400 /usr/local/cuda/bin/ncu --kernel-name regex:bvh_closest_hit --section SpeedOfLight \
                      --section WarpStateStats --section SchedulerStats --section MemoryWorkloadAnalysis \
                      --section InstructionStats --section LaunchStats --section Occupancy \
                      python3 benchmarks/brute_force.py --scene dragon --splits 0 --variants "tree scalar" tree wide \
                      --repeats 1 --rays 1048576 --res 1024 ;;
        pass-parts)  # a path pass's wall time beyond its kernels: samples, image, copy, host check, dispatch
                  stage pass-parts-cornell 90 python3 benchmarks/pass_parts.py --scene cornell
                  stage pass-parts-dragon 90 python3 benchmarks/pass_parts.py --scene dragon
                  stage profile-image-cornell 60 python3 benchmarks/gpu_profile.py image-cornell --size 512 --repeats 5 --top 12 ;;
        profile-rays) stage profile-rays 60 python3 benchmarks/gpu_profile.py rays-dragon --size 1024 --repeats 10 ;;
        ahead)    # compacted GPU bounces that trace the rays they make (`path.GPU_TRACE_AHEAD`, the default)
                  # against each bounce tracing its own rays first, on the environment-lit dragon (the Cornell
                  # box's pass is not compacted)
                  stage path-ahead 200 python3 benchmarks/path_chunks.py --size 512 --repeats 9 --scenes dragon \
                      --knobs "" GPU_TRACE_AHEAD=False "" GPU_TRACE_AHEAD=False ;;
        last-rays)  # the last vertex's rays tested against the emitters with an any-hit query (`path.LAST_RAYS_EMITTERS`,
                  # the default) against their closest hits, on the Cornell box (whole-batch bounces), twice in one
                  # process; then that pass's kernels
                  stage path-last-rays 200 python3 benchmarks/path_chunks.py --size 512 --repeats 9 --scenes cornell \
                      --knobs "" LAST_RAYS_EMITTERS=0 "" LAST_RAYS_EMITTERS=0
                  stage profile-path-cornell 70 python3 benchmarks/gpu_profile.py path-cornell --size 512 --repeats 5 ;;
        last-rays-compile)  # the Cornell box's first call (tracing + compilation, no persistent cache) in fresh processes,
                  # the last rays to the emitters (default) and to their closest hits, alternating, three of each
                  for i in 1 2 3; do
                      for k in "" LAST_RAYS_EMITTERS=0; do
                          JAXRT_CACHE=off stage "path-first-${k:-default}" 90 python3 benchmarks/path_chunks.py --size 512 \
                              --repeats 3 --scenes cornell --no-off --knobs "$k"
                      done
                  done ;;
        pack)     # the whole-batch GPU bounces' ray queries packed (`path.GPU_PACK_RAYS`) and the last rays' emitter
                  # test without exact edge signs (`path.LAST_RAYS_EXACT`), on the Cornell box, twice in one process
                  stage path-pack 200 python3 benchmarks/path_chunks.py --size 512 --repeats 9 --scenes cornell \
                      --knobs "" LAST_RAYS_EXACT=False GPU_PACK_RAYS=True GPU_PACK_RAYS=True,LAST_RAYS_EXACT=False \
                      "" LAST_RAYS_EXACT=False GPU_PACK_RAYS=True GPU_PACK_RAYS=True,LAST_RAYS_EXACT=False ;;
        last-rays-compile2)  # the Cornell box's first call in fresh processes (no persistent cache): the last rays to the
                  # emitters with exact edge signs (default) and without, and to their closest hits; alternating, three of each
                  for i in 1 2 3; do
                      for k in "" LAST_RAYS_EXACT=False LAST_RAYS_EMITTERS=0; do
                          JAXRT_CACHE=off stage "path-first-${k:-default}" 90 python3 benchmarks/path_chunks.py --size 512 \
                              --repeats 3 --scenes cornell --no-off --knobs "$k"
                      done
                  done ;;
        profile-pack)  # the Cornell box's kernels with the ray queries packed (`path.GPU_PACK_RAYS`)
                  stage profile-pack 70 python3 -c "import sys; sys.path.insert(0, 'benchmarks'); sys.argv = ['gpu_profile.py', \
                      'path-cornell', '--size', '512', '--repeats', '5', '--top', '40']; from jaxrt.integrators import path as P; \
                      P.GPU_PACK_RAYS = True; import gpu_profile; sys.exit(gpu_profile.main())" ;;
        pack-compile)  # the Cornell box's first call in fresh processes (no persistent cache): the defaults against the
                  # session's start (last rays to their closest hits, no ray order); then the pass of each in one process
                  for i in 1 2 3; do
                      for k in "" LAST_RAYS_EMITTERS=0,GPU_PACK_RAYS=False; do
                          JAXRT_CACHE=off stage "path-first-${k:-default}" 90 python3 benchmarks/path_chunks.py --size 512 \
                              --repeats 3 --scenes cornell --no-off --knobs "$k"
                      done
                  done
                  stage path-pack-ab 120 python3 benchmarks/path_chunks.py --size 512 --repeats 9 --scenes cornell \
                      --knobs "" LAST_RAYS_EMITTERS=0,GPU_PACK_RAYS=False "" LAST_RAYS_EMITTERS=0,GPU_PACK_RAYS=False ;;
        *)        echo "unknown stage $s" | tee -a "$LOG" ;;
    esac
done
