import click
@click.command('weights-lut')
def command():
    pass
