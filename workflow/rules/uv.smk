# UV (DESIGN section 2): xatlas texture coordinates for the initial mesh, uv/mesh.obj (OBJ
# convention, v up; see recon.uv). The whole uv/ folder is replaced atomically. The input is
# get_init_mesh: the capture's init_mesh.ply when it has one, so init_mesh is then skipped.


rule uv:
    input:
        check=f"{RESULTS}/{{capture}}/check/check.json",
        mesh=get_init_mesh,
    output:
        mesh=f"{RESULTS}/{{capture}}/uv/mesh.obj",
    log:
        f"{RESULTS}/{{capture}}/logs/uv.log",
    benchmark:
        f"{RESULTS}/{{capture}}/benchmarks/uv.tsv"
    conda:
        "../../envs/recon.yaml"
    params:
        capture_files=capture_files(get_init_mesh),
        settings=get_settings("uv"),
    script:
        "../scripts/uv.py"
