import click
@click.command('calibrate-noise')
def command():
    pass
