# Sourced by pinned.sh and queue_worker.sh: the worktree a long run is started from.
#
#   pinned_worktree <clone root> <commit>     # prints <clone>/../wt-<short commit>
#
# Creates the worktree of <commit> beside the clone once (a detached checkout: clean provenance, whatever the clone's
# own tree holds later) and links every dataset folder of the clone's datasets/ into it (datasets are identified by
# content, not path). Fails (status 1) on a commit git does not know.
pinned_worktree() {
  local root="$1" commit wt d name
  commit="$(git -C "$root" rev-parse --short "$2")" || return 1
  wt="$root/../wt-$commit"
  [ -e "$wt/.git" ] || git -C "$root" worktree add --detach "$wt" "$commit" >/dev/null || return 1
  for d in "$root"/datasets/*/; do
    name="$(basename "$d")"; [ -e "$wt/datasets/$name" ] || ln -s "$root/datasets/$name" "$wt/datasets/$name"
  done
  (cd "$wt" && pwd)
}
