# Initial mesh (DESIGN section 2): a watertight, manifold, coarse mesh in the cameras.json
# frame (visual hull of the masks; see recon.init_mesh). The whole init_mesh/ folder is
# replaced atomically; mesh.ply is the declared output.
#
# Skipping: a capture with its own init_mesh.ply never needs this rule: get_init_mesh points
# later stages straight at that file. Asked for explicitly, the rule validates and copies it.


rule init_mesh:
    input:
        cameras=get_cameras,
        masks=get_view_masks,
    output:
        mesh=f"{RESULTS}/{{capture}}/init_mesh/mesh.ply",
    log:
        f"{RESULTS}/{{capture}}/logs/init_mesh.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/init_mesh.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        masks_dir=get_view_masks_dir,
        plane=get_plane,
        sparse=untracked(get_sparse_dir),
        views=untracked(get_views_dir),
        given=untracked(get_given_init_mesh),
        capture_files=capture_files(get_given_init_mesh),
        settings=get_settings("init_mesh"),
    script:
        "../scripts/init_mesh.py"
