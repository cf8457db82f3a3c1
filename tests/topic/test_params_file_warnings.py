"""Topic level, real processes: a params file written for another node is not ignored
without a word (rcl would start the node on its defaults): one warning naming the
sections the file has."""

from harness import INSTALL_DIR, executable, wait_for


def test_a_params_file_for_another_node_is_a_warning_naming_its_sections(spawn):
    params = INSTALL_DIR / 'sfs_stereo_node' / 'share' / 'sfs_stereo_node' / 'params'
    node = spawn(
        [
            executable('curve_recon_node'),
            '--ros-args',
            '--params-file',
            params / 'sfs_stereo_node.yaml',
            '-p',
            'spacng:=0.01',
        ]
    )
    # The file's warnings are logged once the node is constructed, i.e. after its 'ready:'.
    wait_for(
        lambda: 'ready:' in node.output() and 'has no section' in node.output(),
        60.0,
        'curve_recon_node to start and warn about the params file',
    )
    output = node.output()
    warnings = [line for line in output.splitlines() if '[WARN]' in line]
    assert any(
        'has no section for /curve_recon_node (its sections: sfs_stereo_node)' in line
        for line in warnings
    ), output
    assert any('spacng (did you mean spacing?)' in line for line in warnings), output
    assert node.alive() and 'Traceback' not in output
