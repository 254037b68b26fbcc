#!/usr/bin/env bash
# Spread a large batch of CL files over many processes, or over many hosts, with GNU parallel.
#
#   scripts/batch-parallel.sh -m MACHINE -o OUTDIR [-j N] [-S SSHLOGIN]... [-c CSCAM] [FILE...] [-- POST-OPTIONS...]
#
# Every CL file is an independent `cscam post FILE -m MACHINE -o OUTDIR/<stem>.ngc` run (FILEs from the
# arguments, else one per line on stdin). Each run writes its NC program atomically (a temporary beside the
# target, renamed) after the safety gate, and its own log (OUTDIR/logs/<stem>.json, .err): no two runs share a
# path. The summary OUTDIR/summary.tsv lists the files in input order, whatever order they finished in.
# With -S the runs go to other hosts (GNU parallel's --sshlogin); cscam, the machine file, the CL files and
# OUTDIR must then be at the same paths on every host (a shared file system), as in a cluster's home directory.
#
# Exit status (what it means, as for cscam itself):
#   0  every file converted;
#   2  bad input: at least one file was refused (bad CL, unreachable point, the gate), or bad arguments;
#      the others were converted;
#   3  a run failed for another reason (internal error, crash, cscam or a host not reachable).
set -uo pipefail

usage() {
  sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit 2
}

machine="" outdir="" jobs="${CSCAM_PARALLEL_JOBS:-}" cscam="" sshlogins=()
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
while (($#)); do
  case "$1" in
    -m) machine="${2:-}"; shift 2 || usage ;;
    -o) outdir="${2:-}"; shift 2 || usage ;;
    -j) jobs="${2:-}"; shift 2 || usage ;;
    -S) sshlogins+=(--sshlogin "${2:-}"); shift 2 || usage ;;
    -c) cscam="${2:-}"; shift 2 || usage ;;
    -h|--help) usage ;;
    --) break ;;
    -*) echo "batch-parallel: unknown option $1" >&2; usage ;;
    *) break ;;
  esac
done
files=()
while (($#)) && [[ "$1" != "--" ]]; do files+=("$1"); shift; done
[[ "${1:-}" == "--" ]] && shift
post_options=("$@")
[[ -n "$machine" && -n "$outdir" ]] || { echo "batch-parallel: -m MACHINE and -o OUTDIR are required" >&2; usage; }
if ((${#files[@]} == 0)); then
  mapfile -t files
  [[ ${#files[@]} -gt 0 ]] || { echo "batch-parallel: no CL files (arguments or stdin)" >&2; exit 2; }
fi
command -v parallel >/dev/null || { echo "batch-parallel: GNU parallel is not installed" >&2; exit 3; }
if [[ -z "$cscam" ]]; then
  for c in "$here/../build/cscam" "$(command -v cscam || true)"; do [[ -x "$c" ]] && { cscam="$c"; break; }; done
fi
[[ -x "$cscam" ]] || { echo "batch-parallel: cscam not found (give it with -c)" >&2; exit 3; }
cscam="$(cd "$(dirname "$cscam")" && pwd)/$(basename "$cscam")"

# Absolute paths: a remote host's working directory is not ours. One output per stem, known before any run.
declare -A seen
abs=()
for f in "${files[@]}"; do
  [[ -f "$f" ]] || { echo "batch-parallel: $f: no such CL file" >&2; exit 2; }
  a="$(cd "$(dirname "$f")" && pwd)/$(basename "$f")"
  stem="$(basename "${f%.*}")"
  if [[ -n "${seen[$stem]:-}" ]]; then
    echo "batch-parallel: $f and ${seen[$stem]} would both write $stem.ngc: give the files distinct names" >&2
    exit 2
  fi
  seen[$stem]="$f"
  abs+=("$a")
done
[[ -f "$machine" ]] && machine="$(cd "$(dirname "$machine")" && pwd)/$(basename "$machine")"
mkdir -p "$outdir/logs" || exit 3
outdir="$(cd "$outdir" && pwd)"

# One process per file; -j defaults to the cores of each host. The joblog records every run's exit code.
joblog="$outdir/logs/joblog.tsv"
rm -f "$joblog"
# The command is run by a shell (locally or on the host): the fixed words are quoted here, {} by parallel.
q() {
  local w=() a
  for a in "$@"; do w+=("$(printf '%q' "$a")"); done
  echo "${w[*]}"
}
post_q=""
((${#post_options[@]})) && post_q="$(q "${post_options[@]}")"
printf '%s\n' "${abs[@]}" |
  parallel --will-cite --keep-order --joblog "$joblog" ${jobs:+-j "$jobs"} "${sshlogins[@]}" \
    "$(q "$cscam") post {} --machine $(q "$machine") -o $(q "$outdir")/{/.}.ngc --json $post_q" \
    "> $(q "$outdir")/logs/{/.}.json 2> $(q "$outdir")/logs/{/.}.err"

# The summary in input order; the exit status from every run's own exit code (not from parallel's count).
worst=0
{
  printf 'file\tstatus\texit\tnc\n'
  for i in "${!abs[@]}"; do
    a="${abs[$i]}"
    stem="$(basename "${a%.*}")"
    # joblog columns: Seq (input order, 1-based) ... Exitval Signal Command
    rc="$(awk -F'\t' -v seq=$((i + 1)) 'NR > 1 && $1 == seq { print $7 ($8 != 0 ? "+signal" $8 : "") }' "$joblog" 2>/dev/null | tail -n1)"
    case "$rc" in
      0) status=ok ;;
      2) status=refused; ((worst < 2)) && worst=2 ;;
      *) status=error; worst=3 ;;
    esac
    printf '%s\t%s\t%s\t%s\n' "$a" "$status" "${rc:-not-run}" "$([[ $status == ok ]] && echo "$outdir/$stem.ngc" || echo -)"
  done
} >"$outdir/summary.tsv"
n_ok=$(awk -F'\t' 'NR > 1 && $2 == "ok"' "$outdir/summary.tsv" | wc -l)
echo "batch-parallel: $n_ok of ${#abs[@]} files converted; summary in $outdir/summary.tsv" >&2
awk -F'\t' 'NR > 1 && $2 != "ok" { print $1 }' "$outdir/summary.tsv" | while read -r f; do
  echo "  $(basename "$f"): $(head -c 400 "$outdir/logs/$(basename "${f%.*}").err")" >&2
done
exit "$worst"
